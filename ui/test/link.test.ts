import { describe, expect, it } from "vitest";
import { LinkMonitor, restartNote } from "../src/link";

describe("link monitor", () => {
  it("says nothing on the first connect, a standing line while lost, a notice when back", () => {
    let t = 1000;
    const m = new LinkMonitor(() => t);
    expect(m.update("connecting")).toEqual({ banner: null, notice: null });
    expect(m.update("open")).toEqual({ banner: null, notice: null });
    t = 2000;
    const lost = m.update("closed");
    expect(lost.banner).toMatch(/was lost 0 s ago; reconnecting \(attempt 1\)/);
    expect(lost.banner).toMatch(/entered on this screen is kept/);
    t = 5000;
    m.update("connecting");
    expect(m.update("closed").banner).toMatch(/lost 3 s ago; reconnecting \(attempt 2\)/);
    expect(m.update("open")).toEqual({ banner: null, notice: "Reconnected to the daemon." });
    expect(m.update("open").notice).toBeNull();
  });

  it("tells a daemon never reached from one lost", () => {
    const m = new LinkMonitor(() => 0);
    m.update("connecting");
    expect(m.update("closed").banner).toMatch(/cannot be reached; retrying \(attempt 1\)/);
    expect(m.update("open").notice).toBeNull(); // never was up: nothing to "re"connect
  });

  it("notices a restart by the daemon's start time", () => {
    expect(restartNote(null, "2026-11-22T10:00:00.000Z")).toBeNull();
    expect(restartNote("2026-11-22T10:00:00.000Z", "2026-11-22T10:00:00.000Z")).toBeNull();
    expect(restartNote("2026-11-22T10:00:00.000Z", "2026-11-22T10:05:01.250Z")).toMatch(/restarted \(at 2026-11-22 10:05:01 UTC\)/);
  });
});

import { TrackerMonitor } from "../src/link";
describe("tracker monitor", () => {
  it("is quiet until the tracker has streamed, then says when it stops and when it is back", () => {
    let t = 0;
    const m = new TrackerMonitor(() => t);
    expect(m.update("connecting")).toEqual({ banner: null, notice: null }); // starting up: no alarm
    expect(m.update("streaming")).toEqual({ banner: null, notice: null });
    t = 1000;
    expect(m.update("recovering", "tcp 127.0.0.1:9: connection refused").banner)
      .toMatch(/stopped streaming 0 s ago \(now recovering: tcp 127.0.0.1:9: connection refused\).*registration that is running goes on/);
    t = 6000;
    expect(m.update("connecting").banner).toMatch(/stopped streaming 5 s ago \(now connecting\)/);
    expect(m.update("streaming")).toEqual({ banner: null, notice: "The tracker is streaming again." });
    expect(m.update("disabled")).toEqual({ banner: null, notice: null });
  });
});
