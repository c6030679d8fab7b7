// vsmd: the daemon. Parses arguments and runs the Application; everything else is in server/.
#include <csignal>
#include <iostream>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/app/application.hpp"
#include "server/app/signals.hpp"
#include "server/config/config.hpp"

using namespace vsm;

int main(int argc, char** argv) {
  server::CommandLine commandLine;
  try {
    commandLine = server::parseCommandLine(std::vector<std::string>(argv + 1, argv + argc));
  } catch (const core::Error& e) {
    std::cerr << "vsmd: " << e.what() << "\n";
    return 2;
  }
  if (commandLine.help) {
    std::cout << server::commandLineUsage();
    return 0;
  }
  if (commandLine.version) {
    std::cout << "vsmd " << server::version() << "\n";
    return 0;
  }
  try {
    server::blockTerminationSignals();  // before any thread starts, so all inherit the mask
    server::Application app(std::move(commandLine.config));
    const server::SignalWaiter signals([&app](int signal) {
      core::log::info(signal == SIGTERM ? "SIGTERM received" : "SIGINT received");
      app.stop();
    });
    app.run();
    return 0;
  } catch (const core::Error& e) {
    core::log::error(e.what());
    return 1;
  } catch (const std::exception& e) {
    core::log::error(std::string("unexpected: ") + e.what());
    return 1;
  }
}
