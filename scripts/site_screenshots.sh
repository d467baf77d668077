#!/usr/bin/env bash
# Screenshots and a table audit of the built site in headless Chromium at 1400 px (for reading the pages as a
# newcomer would, and for calibrating the build test's table-width estimate; not run by CI, which has no browser).
# Chromium comes from the npm registry (@sparticuz/chromium ships the binary in its package, so nothing else is
# downloaded); puppeteer-core drives it.  Needs node and npm.
#
#   .venv/bin/mkdocs build --strict && bash scripts/site_screenshots.sh [OUT] [PAGE ...]
#
# OUT: /tmp/site_screenshots by default; PAGE: paths under the site (default: Home, Getting started, Study results,
# Case studies).  SITE=DIR: the built site (default site/).  Each page gives OUT/<name>_top.png (the first 1400 x
# 900 px) and the full page in parts of 8,000 px (OUT/<name>_part<k>.png).
#
# QUERIES="install;resume;GPU;own data" also types each query into the site's search box and prints the first five
# results (the page titles the search shows).
#
# AUDIT=1 measures every table of every page instead of taking screenshots: OUT/tables.json holds, per table, the
# page, its header, the width its scroll box shows (clientWidth), the width it needs (scrollWidth) and its natural
# narrowest width (its min-content width); each table hidden in part behind
# a scroll bar is printed.  `python scripts/site_audit.py OUT/tables.json SITE` compares them with the build test's
# estimate (docs_hooks/site_checks.py).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-/tmp/site_screenshots}
shift || true
SITE=${SITE:-site}
PAGES=("$@")
[ ${#PAGES[@]} -gt 0 ] || PAGES=(index.html getting-started/index.html study-results/index.html case-studies/index.html)
if [ -n "${AUDIT:-}" ]; then
    mapfile -t PAGES < <(cd "$SITE" && find . -name index.html ! -path './search/*' ! -path './assets/*' | sed 's|^\./||' | sort)
fi
[ -f "$SITE/index.html" ] || { echo "error: $SITE/index.html: build the site first (mkdocs build --strict)" >&2; exit 2; }
TOOLS=${GRAF_SCREENSHOT_TOOLS:-/tmp/graf_screenshot_tools}
if [ ! -d "$TOOLS/node_modules/puppeteer-core" ]; then
    mkdir -p "$TOOLS"
    (cd "$TOOLS" && npm init -y >/dev/null && npm install --silent --no-audit --no-fund @sparticuz/chromium@153 puppeteer-core@24)
fi
mkdir -p "$OUT"
PORT=${PORT:-8765}
python3 -m http.server "$PORT" --directory "$SITE" >/dev/null 2>&1 &
SERVER=$!
trap 'kill $SERVER' EXIT
sleep 1
cat > "$TOOLS/shoot.mjs" <<'JS'
import chromium from '@sparticuz/chromium';
import puppeteer from 'puppeteer-core';
import {writeFileSync} from 'node:fs';
const [out, port, ...pages] = process.argv.slice(2);
const browser = await puppeteer.launch({args: chromium.args, executablePath: await chromium.executablePath(),
                                        headless: true, defaultViewport: {width: 1400, height: 900}});
const page = await browser.newPage();
const audit = [];
for (const p of pages) {
  await page.goto(`http://localhost:${port}/${p}`, {waitUntil: 'networkidle0'});
  const name = p.replace(/\/?index\.html$/, '').replace(/\//g, '_') || 'home';
  if (process.env.AUDIT) {
    const tables = await page.$$eval('article table', ts => ts.map((t, i) => {
      const box = t.closest('.md-typeset__scrollwrap') || t.parentElement;
      const seen = {client: box.clientWidth, scroll: box.scrollWidth, table: t.offsetWidth};
      // the table at its narrowest (its min-content width): each column as wide as its longest unbreakable content
      t.style.width = 'min-content';
      t.style.maxWidth = 'none';
      const narrowest = t.offsetWidth;
      const cols = [...(t.rows[0]?.cells || [])].map(c => c.offsetWidth);
      t.style.width = '';
      t.style.maxWidth = '';
      const head = [...(t.rows[0]?.cells || [])].map(c => c.textContent.trim());
      return {index: i, head, ...seen, narrowest, cols, font: getComputedStyle(t).fontFamily};
    }));
    for (const t of tables) {
      audit.push({page: p, ...t});
      if (t.scroll > t.client) console.log(`${p}: table ${t.index} (${t.head.slice(0, 4).join(' | ')}): ${t.scroll - t.client} px behind a scroll bar`);
    }
    continue;
  }
  await page.screenshot({path: `${out}/${name}_top.png`});
  const height = await page.evaluate(() => document.documentElement.scrollHeight);
  // Chromium repeats tiles past about 16,000 px in one capture: the full page comes in parts of 8,000 px
  const part = 8000;
  for (let y = 0, k = 1; y < height; y += part, k++) {
    await page.screenshot({path: `${out}/${name}_part${k}.png`, captureBeyondViewport: true,
                           clip: {x: 0, y, width: 1400, height: Math.min(part, height - y)}});
  }
  console.log(`${name}: ${height} px tall, ${Math.ceil(height / part)} part(s)`);
}
if (process.env.AUDIT) {
  writeFileSync(`${out}/tables.json`, JSON.stringify(audit, null, 1));
  console.log(`${audit.length} tables on ${pages.length} pages; ${audit.filter(t => t.scroll > t.client).length} behind a scroll bar`);
}
for (const q of (process.env.QUERIES || '').split(';').filter(Boolean)) {
  await page.goto(`http://localhost:${port}/index.html`, {waitUntil: 'networkidle0'});
  await page.click('label.md-search__icon, .md-search__input').catch(() => {});
  await page.focus('.md-search__input');
  await page.keyboard.type(q);
  await page.waitForSelector('.md-search-result__item', {timeout: 10000}).catch(() => {});
  await new Promise(r => setTimeout(r, 1500));
  const hits = await page.$$eval('.md-search-result__item > .md-search-result__link',
    els => els.map(e => (e.querySelector('h1, h2')?.textContent || '').trim() + ' <' + e.getAttribute('href') + '>'));
  const count = await page.$eval('.md-search-result__meta', e => e.textContent.trim()).catch(() => 'n/a');
  console.log(`search "${q}": ${count}; first: ${hits.slice(0, 5).join(' | ')}`);
  await page.screenshot({path: `${out}/search_${q.replace(/\W+/g, '_')}.png`});
}
await browser.close();
JS
(cd "$TOOLS" && node shoot.mjs "$(realpath "$OUT")" "$PORT" "${PAGES[@]}")
