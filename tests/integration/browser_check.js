// Loads a page of a running vsmd in headless Chromium (Debian's /usr/bin/chromium, driven by npm
// playwright-core), waits until the page's own counters say every requested tile is in, and
// writes a screenshot. Prints one JSON line: the page's counters, the console errors, the failed
// requests and how long it took. The checks are viewer_test.py's; this only observes.
//
// With a steps file (JSON array), it then goes on in the same page, step by step:
//   {"name": N, "run": "JS"}      evaluates JS in the page (statements; `return` a JSON value)
//   {"name": N, "until": "JS"}    waits until the expression is true and the page settles again
//   {"name": N, "screenshot": P}  a screenshot to P
// and reports, per step, its name, its value and the page's state after it ("steps").
//
// Usage: node browser_check.js <node-tools prefix> <url> <state variable> <screenshot.png>
//        <timeout seconds> [<steps.json>]
'use strict';

const fs = require('fs');
const path = require('path');

const [prefix, url, stateName, screenshot, timeoutText, stepsFile] = process.argv.slice(2);
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
    // Until `condition` (an expression, or none) holds and the page has been idle for 1.5 s in a
    // row (the renderer may start new loads right after finishing some); the page's state then.
    const settle = async (condition, since) => {
      let idleSince = null;
      let state = null;
      for (;;) {
        state = await page.evaluate((name) => JSON.parse(JSON.stringify(window[name] || null)),
          stateName);
        const now = Date.now();
        if (state && (state.error || state.failed > 0)) {
          return state;
        }
        const met = !condition || await page.evaluate(condition);
        if (state && state.idle && met) {
          idleSince = idleSince === null ? now : idleSince;
          if (now - idleSince >= 1500) {
            return state;
          }
        } else {
          idleSince = null;
        }
        if (now - since > timeout) {
          out.timedOut = true;
          return state;
        }
        await page.waitForTimeout(250);
      }
    };
    out.state = await settle(null, started);
    await page.screenshot({ path: screenshot, timeout });
    out.screenshot = screenshot;
    if (stepsFile && !out.timedOut) {
      out.steps = [];
      for (const step of JSON.parse(fs.readFileSync(stepsFile, 'utf8'))) {
        const done = { name: step.name, value: null };
        if (step.run) {
          done.value = await page.evaluate(`(async () => { ${step.run} })()`);
        } else if (step.until) {
          done.state = await settle(step.until, Date.now());
        } else if (step.screenshot) {
          await page.screenshot({ path: step.screenshot, timeout });
          done.value = step.screenshot;
        }
        done.state = done.state || await page.evaluate(
          (name) => JSON.parse(JSON.stringify(window[name] || null)), stateName);
        out.steps.push(done);
        if (out.timedOut) {
          break;
        }
      }
    }
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
