// Loads a page of a running vsmd in headless Chromium (Debian's /usr/bin/chromium, driven by npm
// playwright-core), waits until the page's own counters say every requested tile is in, and
// writes a screenshot. Prints one JSON line: the page's counters, the console errors, the failed
// requests and how long it took. The checks are viewer_test.py's; this only observes.
//
// Usage: node browser_check.js <node-tools prefix> <url> <state variable> <screenshot.png>
//        <timeout seconds>
'use strict';

const path = require('path');

const [prefix, url, stateName, screenshot, timeoutText] = process.argv.slice(2);
const { chromium } = require(path.join(prefix, 'node_modules', 'playwright-core'));
const timeout = Number(timeoutText || 60) * 1000;

// Exactly the flags CI runs Chromium with (issue 6).
const FLAGS = ['--headless', '--no-sandbox', '--disable-gpu', '--enable-unsafe-swiftshader',
  '--disable-background-networking', '--disable-component-update', '--disable-sync',
  '--no-first-run'];

async function main() {
  const started = Date.now();
  const browser = await chromium.launch({
    executablePath: process.env.VSM_CHROMIUM || '/usr/bin/chromium',
    headless: true,
    ignoreDefaultArgs: true,
    args: [...FLAGS, '--remote-debugging-pipe', 'about:blank'],
    timeout: 30000,
  });
  const out = { url, consoleErrors: [], failedRequests: [], offHost: [] };
  try {
    const context = await browser.newContext({ viewport: { width: 1024, height: 768 } });
    const page = await context.newPage();
    const host = new URL(url).host;
    page.on('console', (message) => {
      if (message.type() === 'error') {
        out.consoleErrors.push(message.text().slice(0, 500));
      }
    });
    page.on('pageerror', (error) => out.consoleErrors.push(String(error).slice(0, 500)));
    page.on('requestfailed', (request) => {
      const failure = request.failure();
      out.failedRequests.push(`${request.url()}: ${failure && failure.errorText}`);
    });
    page.on('request', (request) => {
      const u = new URL(request.url());
      if ((u.protocol === 'http:' || u.protocol === 'https:') && u.host !== host) {
        out.offHost.push(request.url());
      }
    });
    await page.goto(url, { waitUntil: 'load', timeout });
    // Idle for a second in a row: the renderer may start new loads right after finishing some.
    let idleSince = null;
    let state = null;
    for (;;) {
      state = await page.evaluate((name) => JSON.parse(JSON.stringify(window[name] || null)),
        stateName);
      const now = Date.now();
      if (state && (state.error || state.failed > 0)) {
        break;
      }
      if (state && state.idle) {
        idleSince = idleSince === null ? now : idleSince;
        if (now - idleSince >= 1500) {
          break;
        }
      } else {
        idleSince = null;
      }
      if (now - started > timeout) {
        out.timedOut = true;
        break;
      }
      await page.waitForTimeout(250);
    }
    out.state = state;
    await page.screenshot({ path: screenshot, timeout: 30000 });
    out.screenshot = screenshot;
  } finally {
    out.seconds = (Date.now() - started) / 1000;
    await browser.close();
  }
  process.stdout.write(JSON.stringify(out) + '\n');
}

main().catch((error) => {
  process.stderr.write(String(error && error.stack ? error.stack : error) + '\n');
  process.exit(1);
});
