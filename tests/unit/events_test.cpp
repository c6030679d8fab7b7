// The event hub of GET /v1/events: fan-out in id order, per-job coalescing, the per-subscriber
// bound and the drop, the subscriber cap, heartbeats and close.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "server/events/event_hub.hpp"
#include "server/http/message.hpp"

namespace vsm::server::events {
namespace {

using namespace std::chrono_literals;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

/// A clock the test moves.
struct FakeClock {
  std::shared_ptr<Clock::time_point> now = std::make_shared<Clock::time_point>(Clock::now());
  std::function<Clock::time_point()> fn() const {
    return [now = now] { return *now; };
  }
  void advance(Clock::duration by) const { *now += by; }
};

HubOptions options(const FakeClock& clock) {
  HubOptions o;
  o.now = clock.fn();
  return o;
}

/// What pull() gives, and whether the stream goes on.
struct Pulled {
  std::string text;
  bool open = true;
};
Pulled pull(http::BodyStream& stream) {
  Pulled out;
  out.open = stream.pull(out.text);
  return out;
}

/// The events in SSE text: (id, event, data); comments and blank lines skipped.
struct Event {
  std::string id;
  std::string name;
  json data;
};
std::vector<Event> parse(const std::string& text) {
  std::vector<Event> out;
  Event current;
  bool any = false;
  std::size_t start = 0;
  while (start < text.size()) {
    const std::size_t end = text.find('\n', start);
    const std::string line = text.substr(start, end - start);
    start = end == std::string::npos ? text.size() : end + 1;
    if (line.empty()) {
      if (any) {
        out.push_back(current);
      }
      current = {};
      any = false;
    } else if (line.starts_with("id: ")) {
      current.id = line.substr(4);
      any = true;
    } else if (line.starts_with("event: ")) {
      current.name = line.substr(7);
      any = true;
    } else if (line.starts_with("data: ")) {
      current.data = json::parse(line.substr(6));
      any = true;
    }
  }
  return out;
}

TEST(EventHub, EverySubscriberGetsEveryEventInIdOrder) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto a = hub.subscribe();
  auto b = hub.subscribe();
  auto c = hub.subscribe();
  hub.publish("published", {{"model", "m"}, {"version", 2}});
  hub.publish("job_end", {{"job", "j1"}, {"state", "succeeded"}});
  const Pulled first = pull(*a);
  EXPECT_TRUE(first.open);
  EXPECT_EQ(first.text, pull(*b).text);
  EXPECT_EQ(first.text, pull(*c).text);
  const auto events = parse(first.text);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[0].id, "1");
  EXPECT_EQ(events[0].name, "published");
  EXPECT_EQ(events[0].data["version"], 2);
  EXPECT_EQ(events[1].id, "2");
  EXPECT_EQ(events[1].name, "job_end");
  EXPECT_TRUE(pull(*a).text.empty());  // taken once
  EXPECT_EQ(hub.lastId(), 2U);
}

TEST(EventHub, DataIsOneLineEvenWithNewlinesInStrings) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto a = hub.subscribe();
  hub.publish("job_end", {{"error", "line one\nline two\r\n"}});
  const std::string text = pull(*a).text;
  EXPECT_EQ(std::count(text.begin(), text.end(), '\n'), 4);  // id, event, data, blank line
  EXPECT_EQ(parse(text)[0].data["error"], "line one\nline two\r\n");
}

TEST(EventHub, SubscriberSeesOnlyEventsAfterItSubscribed) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto early = hub.subscribe();
  hub.publish("job", {{"n", 1}});
  auto late = hub.subscribe();
  hub.publish("job", {{"n", 2}});
  EXPECT_EQ(parse(pull(*early).text).size(), 2U);
  const auto events = parse(pull(*late).text);
  ASSERT_EQ(events.size(), 1U);
  EXPECT_EQ(events[0].id, "2");
}

TEST(EventHub, WakeIsCalledOnceUntilThePull) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto a = hub.subscribe();
  std::atomic<int> wakes = 0;
  a->start([&wakes] { ++wakes; });
  EXPECT_EQ(wakes, 0);  // nothing queued yet
  hub.publish("job", {{"n", 1}});
  hub.publish("job", {{"n", 2}});
  EXPECT_EQ(wakes, 1);
  pull(*a);
  hub.publish("job", {{"n", 3}});
  EXPECT_EQ(wakes, 2);
}

TEST(EventHub, ProgressOfOneJobIsCoalescedToTheNewest) {
  FakeClock clock;
  EventHub hub(options(clock));  // 250 ms
  auto a = hub.subscribe();
  for (int i = 0; i <= 100; ++i) {
    hub.progress("j1", "job", {{"job", "j1"}, {"progress", i / 100.0}});
    clock.advance(1ms);
  }
  hub.tick();  // 100 ms after the first: still within the interval
  auto events = parse(pull(*a).text);
  ASSERT_EQ(events.size(), 1U);  // the first goes at once
  EXPECT_EQ(events[0].data["progress"], 0.0);
  clock.advance(150ms);
  hub.tick();
  events = parse(pull(*a).text);
  ASSERT_EQ(events.size(), 1U);  // the newest held back, at the end of the interval
  EXPECT_EQ(events[0].data["progress"], 1.0);
  clock.advance(1s);
  hub.tick();
  EXPECT_TRUE(pull(*a).text.empty());  // nothing twice
}

TEST(EventHub, ProgressOfDifferentJobsIsNotCoalescedTogether) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto a = hub.subscribe();
  hub.progress("j1", "job", {{"job", "j1"}});
  hub.progress("j2", "job", {{"job", "j2"}});
  EXPECT_EQ(parse(pull(*a).text).size(), 2U);
}

TEST(EventHub, SettledJobSendsNoHeldBackProgressAfterItsEnd) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto a = hub.subscribe();
  hub.progress("j1", "job", {{"progress", 0.1}});
  hub.progress("j1", "job", {{"progress", 0.9}});  // held back
  hub.settle("j1");
  hub.publish("job_end", {{"job", "j1"}});
  clock.advance(1s);
  hub.tick();
  const auto events = parse(pull(*a).text);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events.back().name, "job_end");
}

TEST(EventHub, SubscriberThatDoesNotReadIsDroppedWithAFinalEvent) {
  FakeClock clock;
  HubOptions o = options(clock);
  o.queueEvents = 8;
  EventHub hub(o);
  auto slow = hub.subscribe();
  auto fast = hub.subscribe();
  std::atomic<int> wakes = 0;
  slow->start([&wakes] { ++wakes; });
  for (int i = 0; i < 8; ++i) {
    hub.publish("job", {{"n", i}});
    EXPECT_EQ(parse(pull(*fast).text).size(), 1U);
  }
  EXPECT_FALSE(slow->ended());
  EXPECT_EQ(hub.dropped(), 0U);
  hub.publish("job", {{"n", 8}});  // the ninth does not fit
  EXPECT_TRUE(slow->ended());
  EXPECT_EQ(wakes, 2);  // for the first event, and for the end even though not pulled since
  EXPECT_EQ(hub.dropped(), 1U);
  EXPECT_EQ(hub.subscribers(), 1U);
  const Pulled last = pull(*slow);
  EXPECT_FALSE(last.open);
  const auto events = parse(last.text);
  ASSERT_EQ(events.size(), 1U);  // its backlog is gone: only the final event
  EXPECT_EQ(events[0].name, "dropped");
  EXPECT_EQ(events[0].data["reason"], "queue_full");
  // The others go on.
  hub.publish("job", {{"n", 9}});
  const auto rest = parse(pull(*fast).text);
  ASSERT_EQ(rest.size(), 2U);  // the one that dropped the other, and the next
  EXPECT_EQ(rest[0].id, "9");
  EXPECT_EQ(rest[1].id, "10");
  EXPECT_TRUE(pull(*slow).text.empty());
}

TEST(EventHub, QueueIsBoundedInBytesToo) {
  FakeClock clock;
  HubOptions o = options(clock);
  o.queueBytes = 1024;
  EventHub hub(o);
  auto slow = hub.subscribe();
  const std::string big(300, 'x');
  for (int i = 0; i < 3; ++i) {
    hub.publish("job", {{"blob", big}});
  }
  EXPECT_FALSE(slow->ended());
  hub.publish("job", {{"blob", big}});
  EXPECT_TRUE(slow->ended());
  EXPECT_LT(pull(*slow).text.size(), 1024U);
}

TEST(EventHub, HeartbeatsAreCommentsAndCountAgainstTheBound) {
  FakeClock clock;
  HubOptions o = options(clock);
  o.queueEvents = 3;
  EventHub hub(o);
  auto a = hub.subscribe();
  clock.advance(14s);
  hub.tick();
  EXPECT_TRUE(pull(*a).text.empty());
  clock.advance(1s);
  hub.tick();
  EXPECT_EQ(pull(*a).text, ": ping\n\n");
  for (int i = 0; i < 4; ++i) {  // never read: the fourth ping overflows
    clock.advance(15s);
    hub.tick();
  }
  EXPECT_TRUE(a->ended());
}

TEST(EventHub, SubscribersAreCapped) {
  FakeClock clock;
  HubOptions o = options(clock);
  o.maxSubscribers = 2;
  EventHub hub(o);
  auto a = hub.subscribe();
  auto b = hub.subscribe();
  try {
    hub.subscribe();
    FAIL() << "a third subscriber was taken";
  } catch (const core::Error& e) {
    EXPECT_EQ(e.code(), core::ErrorCode::Unavailable);
  }
  b->stop();  // a connection that went away frees its place
  EXPECT_EQ(hub.subscribers(), 1U);
  auto c = hub.subscribe();
  c.reset();  // so does one destroyed without being stopped
  EXPECT_EQ(hub.subscribers(), 1U);
  EXPECT_NO_THROW(hub.subscribe());
}

TEST(EventHub, OneClientsSubscribersAreCappedWhileOthersAreStillTaken) {
  FakeClock clock;
  HubOptions o = options(clock);
  o.maxSubscribers = 4;
  o.maxSubscribersPerClient = 2;
  EventHub hub(o);
  auto a1 = hub.subscribe("127.0.0.1");
  auto a2 = hub.subscribe("127.0.0.1");
  try {
    hub.subscribe("127.0.0.1");
    FAIL() << "a third subscriber of one client was taken";
  } catch (const core::Error& e) {
    EXPECT_EQ(e.code(), core::ErrorCode::Unavailable);
    EXPECT_NE(std::string(e.what()).find("limits.event_subscribers_per_client"), std::string::npos);
  }
  auto b = hub.subscribe("127.0.0.2");  // another client still gets one
  EXPECT_EQ(hub.subscribers(), 3U);
  a1->stop();  // the client's share frees as its streams go
  auto a3 = hub.subscribe("127.0.0.1");
  a2.reset();
  auto a4 = hub.subscribe("127.0.0.1");
  EXPECT_EQ(hub.subscribers(), 3U);
}

TEST(EventHub, ADroppedSubscriberFreesItsClientsShare) {
  FakeClock clock;
  HubOptions o = options(clock);
  o.maxSubscribersPerClient = 1;
  o.queueEvents = 1;
  EventHub hub(o);
  auto slow = hub.subscribe("127.0.0.1");
  hub.publish("job", {{"n", 1}});
  hub.publish("job", {{"n", 2}});  // overflows its queue: dropped
  EXPECT_EQ(hub.dropped(), 1U);
  EXPECT_NO_THROW(hub.subscribe("127.0.0.1"));
}

TEST(EventHub, CloseEndsEveryStreamAfterWhatItQueued) {
  FakeClock clock;
  EventHub hub(options(clock));
  auto a = hub.subscribe();
  hub.publish("job", {{"n", 1}});
  hub.close();
  EXPECT_TRUE(a->ended());
  const Pulled last = pull(*a);
  EXPECT_FALSE(last.open);
  EXPECT_EQ(parse(last.text).size(), 1U);
  EXPECT_THROW(hub.subscribe(), core::Error);
  hub.publish("job", {{"n", 2}});  // ignored
  EXPECT_EQ(hub.lastId(), 1U);
}

TEST(EventHub, TickerThreadSendsHeldBackProgress) {
  HubOptions o;
  o.progressInterval = 20ms;
  EventHub hub(o);
  hub.start();
  auto a = hub.subscribe();
  hub.progress("j1", "job", {{"progress", 0.1}});
  hub.progress("j1", "job", {{"progress", 0.2}});
  // Polled until both came, with a bound far above the ticker's 50 ms on any machine.
  std::string text;
  const auto deadline = std::chrono::steady_clock::now() + 60s;
  while (parse(text).size() < 2 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(10ms);
    text += pull(*a).text;
  }
  const auto events = parse(text);
  ASSERT_EQ(events.size(), 2U);
  EXPECT_EQ(events[1].data["progress"], 0.2);
}

}  // namespace
}  // namespace vsm::server::events
