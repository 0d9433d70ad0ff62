// What the browser tests of tests/ui share: finding playwright-core and Debian's chromium
// (skip 77 without them, fail without the built UI), starting and stopping cortexfused on a
// configuration file, and a headless touch browser with a fresh profile.
import { spawn } from "node:child_process";
import { createRequire } from "node:module";
import fs from "node:fs";
import net from "node:net";
import path from "node:path";

/** playwright-core's chromium, or exits: 77 (skip) without chromium or ui/node_modules, 1 when
 *  the UI build left no ui/dist. */
export function chromiumOrExit(uiDir) {
  const exe = process.env.CF_CHROMIUM ?? "/usr/bin/chromium";
  if (!fs.existsSync(exe)) { console.log(`SKIP: no ${exe}`); process.exit(77); }
  if (!fs.existsSync(path.join(uiDir, "node_modules", "playwright-core"))) { console.log("SKIP: ui/node_modules missing (npm ci)"); process.exit(77); }
  if (!fs.existsSync(path.join(uiDir, "dist", "index.html"))) { console.error("FAIL: ui/dist/index.html missing: the UI build failed"); process.exit(1); }
  return { chromium: createRequire(path.join(uiDir, "package.json"))("playwright-core").chromium, exe };
}

/** A headless chromium with touch, its profile in `profileDir` (fresh each run). */
export function launchTouchBrowser({ chromium, exe }, profileDir, viewport = { width: 1280, height: 800 }) {
  return chromium.launchPersistentContext(profileDir, {
    executablePath: exe, headless: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
           "--disable-component-update", "--disable-sync"],
    viewport, hasTouch: true,
  });
}

/** Daemons started by a test: start(configFile) resolves to { proc, base } once it listens;
 *  a daemon that exits without stop() is kept in `deaths` with the end of its stderr. */
export class Daemons {
  constructor(bin) { this.bin = bin; this.deaths = []; this.procs = new Set(); }

  start(configFile) {
    return new Promise((resolve, reject) => {
      const proc = spawn(this.bin, ["--config", configFile], { stdio: ["ignore", "pipe", "pipe"] });
      this.procs.add(proc);
      let err = "", out = "";
      proc.stderr.on("data", (d) => { err += d; if (err.length > 20000) err = err.slice(-10000); });
      const t = setTimeout(() => reject(new Error(`daemon did not start in 30 s: ${err.slice(-2000)}`)), 30000);
      proc.stdout.on("data", (d) => {
        out += d;
        const m = /listening on (http:\/\/[^\s]+)/.exec(out);
        if (m) { clearTimeout(t); resolve({ proc, base: m[1].replace(/\/$/, "").replace("0.0.0.0", "127.0.0.1") }); }
      });
      proc.on("exit", (c, sig) => {
        clearTimeout(t);
        this.procs.delete(proc);
        if (!proc.stoppedByTest) this.deaths.push(`cortexfused exited (code ${c}, signal ${sig}) by itself; its stderr ends:\n${err.slice(-6000)}`);
        reject(new Error(`daemon exited ${c}: ${err.slice(-2000)}`));
      });
    });
  }

  /** SIGTERM, SIGKILL after 10 s; resolves once it has exited. */
  async stop(proc) {
    if (!proc || proc.exitCode !== null || proc.signalCode !== null) return;
    proc.stoppedByTest = true;
    proc.kill("SIGTERM");
    await new Promise((r) => { const t = setTimeout(() => { proc.kill("SIGKILL"); r(); }, 10000); proc.on("exit", () => { clearTimeout(t); r(); }); });
  }

  async stopAll() { for (const p of [...this.procs]) await this.stop(p); }
}

/** A TCP port free on 127.0.0.1 just now (for a program that must be told its port up front). */
export function freePort() {
  return new Promise((resolve, reject) => {
    const s = net.createServer();
    s.once("error", reject);
    s.listen(0, "127.0.0.1", () => { const { port } = s.address(); s.close(() => resolve(port)); });
  });
}
