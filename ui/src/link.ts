// What the screen says about the push channel (the live link to the daemon): nothing while it
// is up, a standing line while it is lost (since when, which attempt), a short notice when it
// is back, and whether the daemon restarted meanwhile (its started_utc changed).
import type { PushState } from "./push";

export interface LinkView { banner: string | null; notice: string | null }

export class LinkMonitor {
  private everOpen = false;
  private lostAtMs: number | null = null;
  private tries = 0;

  constructor(private readonly nowMs: () => number = () => Date.now()) {}

  update(s: PushState): LinkView {
    if (s === "open") {
      const wasLost = this.lostAtMs !== null && this.everOpen;
      this.lostAtMs = null;
      this.tries = 0;
      this.everOpen = true;
      return { banner: null, notice: wasLost ? "Reconnected to the daemon." : null };
    }
    if (s === "closed") {
      this.tries++;
      if (this.lostAtMs === null) this.lostAtMs = this.nowMs();
    }
    if (this.lostAtMs === null) return { banner: null, notice: null }; // the first connect
    const secs = Math.max(0, Math.round((this.nowMs() - this.lostAtMs) / 1000));
    return {
      banner: this.everOpen
        ? `The connection to the daemon was lost ${secs} s ago; reconnecting (attempt ${this.tries})… What you entered on this screen is kept.`
        : `The daemon cannot be reached; retrying (attempt ${this.tries})… Check that cortexfused is running.`,
      notice: null,
    };
  }
}

/** A line when the daemon's start time changed (it restarted), else null. */
export function restartNote(prevStartedUtc: string | null, startedUtc: string | undefined): string | null {
  if (!prevStartedUtc || !startedUtc || prevStartedUtc === startedUtc) return null;
  const t = startedUtc.replace("T", " ").replace(/\.\d+Z$|Z$/, "");
  return `The daemon restarted (at ${t} UTC): jobs that were running before have stopped; start them again from Jobs if needed.`;
}

/** What the screen says about the tracker: a standing line from the moment it stops streaming
 *  (after it had streamed) until it streams again, then a notice. */
export class TrackerMonitor {
  private streamed = false;
  private lostAtMs: number | null = null;

  constructor(private readonly nowMs: () => number = () => Date.now()) {}

  update(state: string | undefined, lastError = ""): LinkView {
    if (state === "streaming") {
      const back = this.lostAtMs !== null;
      this.lostAtMs = null;
      this.streamed = true;
      return { banner: null, notice: back ? "The tracker is streaming again." : null };
    }
    if (!this.streamed || !state || state === "disabled") return { banner: null, notice: null };
    if (this.lostAtMs === null) this.lostAtMs = this.nowMs();
    const secs = Math.max(0, Math.round((this.nowMs() - this.lostAtMs) / 1000));
    return {
      banner: `The tracker stopped streaming ${secs} s ago (now ${state.replace(/_/g, " ")}${lastError ? `: ${lastError}` : ""}). ` +
              "Tools are not tracked meanwhile; a registration that is running goes on (it uses the photo, not the tracker). " +
              "Check the tracker's cable and power; it reconnects by itself.",
      notice: null,
    };
  }
}
