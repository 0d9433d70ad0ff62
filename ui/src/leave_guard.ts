// Unsaved marks are not dropped without a word (issue 7, 7.47): a screen with unsaved edits
// registers a check; a hash change away from it is put back and asked about in the UI
// ("Stay" / "Leave without saving"), not through the browser's beforeunload.

export type LeaveDecision =
  | { kind: "go" }                                   // route to the new hash
  | { kind: "ask"; reason: string; back: string; to: string }; // put `back` again, ask about `to`

export class LeaveGuard {
  private check: (() => string | null) | null = null;
  private discardFn: (() => void) | null = null;
  private current = "";
  private allowed: string | null = null;

  /** The screen now shown at `hash` (called by the router); forgets the last screen's check. */
  arrived(hash: string): void { this.current = hash; this.check = null; this.discardFn = null; this.allowed = null; }

  /** The shown screen's check: the words for its unsaved edits, or null when all is saved;
   *  `discard` forgets the edits kept for later (marks_draft.ts) when the person leaves without saving. */
  set(check: () => string | null, discard?: () => void): void { this.check = check; this.discardFn = discard ?? null; }

  /** The person chose "Leave without saving" for `to`: the next change to it goes through, and
   *  the screen's kept edits are dropped. */
  allowOnce(to: string): void { this.allowed = to; this.discardFn?.(); this.discardFn = null; }

  /** The hash became `to`. */
  decide(to: string): LeaveDecision {
    if (to === this.current || this.allowed === to) return { kind: "go" };
    const reason = this.check?.() ?? null;
    return reason ? { kind: "ask", reason, back: this.current, to } : { kind: "go" };
  }
}

/** The words for a photo screen's unsaved marks, or null. */
export function unsavedMarksText(landmarks: boolean, roi: boolean): string | null {
  if (!landmarks && !roi) return null;
  const what = landmarks && roi ? "landmarks and ROI" : landmarks ? "landmarks" : "ROI";
  return `Unsaved ${what} on Photo & marks: stay and tap Save, or leave without saving (the changes are dropped).`;
}
