// Who is using the UI: the kiosk on the cart (loopback, no login: everything) or a user logged
// in with POST /api/login (surgeon, technician, admin: read and change; reviewer: read only).
// The session is kept in sessionStorage (this tab only, gone when the browser closes).

export type Role = "kiosk" | "surgeon" | "technician" | "reviewer" | "admin";
export interface Session { token: string | null; user: string; role: Role; expiresUtc?: string }

export const KIOSK: Session = { token: null, user: "", role: "kiosk" };
const KEY = "cortexfuse.session";
const ROLES: Role[] = ["kiosk", "surgeon", "technician", "reviewer", "admin"];

/** Whether this role may change anything (create cases, start or cancel jobs, edit a case). */
export function canWrite(s: Session): boolean {
  return s.role !== "reviewer";
}

/** The status bar's words for the session. */
export function roleLabel(s: Session): string {
  if (s.role === "kiosk") return "Kiosk (full access)";
  const what = s.role === "reviewer" ? "reviewer, read-only" : s.role;
  return `${s.user} (${what})`;
}

/** The session from POST /api/login's answer; throws naming what is missing. */
export function sessionFromLogin(answer: unknown): Session {
  const a = answer as { token?: unknown; user?: unknown; role?: unknown; expires_utc?: unknown };
  if (!a || typeof a.token !== "string" || !a.token) throw new Error("the login answer has no token");
  if (typeof a.role !== "string" || !ROLES.includes(a.role as Role) || a.role === "kiosk")
    throw new Error(`the login answer has an unknown role (${String(a.role)})`);
  return { token: a.token, user: typeof a.user === "string" ? a.user : "", role: a.role as Role,
           expiresUtc: typeof a.expires_utc === "string" ? a.expires_utc : undefined };
}

export interface KeyValueStore { getItem(k: string): string | null; setItem(k: string, v: string): void; removeItem(k: string): void }

/** The stored session, or null (none, unreadable, or expired at `nowMs`). */
export function loadSession(store: KeyValueStore, nowMs = Date.now()): Session | null {
  let s: Session;
  try {
    s = sessionFromLogin(JSON.parse(store.getItem(KEY) ?? "null"));
  } catch {
    return null;
  }
  if (s.expiresUtc && Date.parse(s.expiresUtc) <= nowMs) { store.removeItem(KEY); return null; }
  return s;
}

export function saveSession(store: KeyValueStore, s: Session | null): void {
  if (!s || !s.token) store.removeItem(KEY);
  else store.setItem(KEY, JSON.stringify({ token: s.token, user: s.user, role: s.role, expires_utc: s.expiresUtc }));
}

/** The push channel's address: `?token=` when logged in (docs/api/push.md). */
export function wsUrl(loc: { protocol: string; host: string }, s: Session): string {
  const base = `${loc.protocol === "https:" ? "wss" : "ws"}://${loc.host}/api/ws`;
  return s.token ? `${base}?token=${encodeURIComponent(s.token)}` : base;
}
