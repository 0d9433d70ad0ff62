import { describe, expect, it } from "vitest";
import { canWrite, KIOSK, loadSession, roleLabel, saveSession, sessionFromLogin, wsUrl, type KeyValueStore } from "../src/session";

const memStore = (): KeyValueStore & { m: Map<string, string> } => {
  const m = new Map<string, string>();
  return { m, getItem: (k) => m.get(k) ?? null, setItem: (k, v) => void m.set(k, v), removeItem: (k) => void m.delete(k) };
};

describe("session", () => {
  it("reads POST /api/login's answer and refuses one without a token or with an unknown role", () => {
    const s = sessionFromLogin({ token: "abc", user: "rita", role: "reviewer", expires_utc: "2030-01-01T00:00:00Z" });
    expect(s).toEqual({ token: "abc", user: "rita", role: "reviewer", expiresUtc: "2030-01-01T00:00:00Z" });
    expect(() => sessionFromLogin({ user: "x", role: "surgeon" })).toThrow(/no token/);
    expect(() => sessionFromLogin({ token: "t", role: "janitor" })).toThrow(/unknown role \(janitor\)/);
    expect(() => sessionFromLogin({ token: "t", role: "kiosk" })).toThrow(/unknown role/);
    expect(() => sessionFromLogin(null)).toThrow();
  });

  it("only the reviewer is read-only", () => {
    expect(canWrite(KIOSK)).toBe(true);
    for (const role of ["surgeon", "technician", "admin"] as const) expect(canWrite({ token: "t", user: "u", role })).toBe(true);
    expect(canWrite({ token: "t", user: "u", role: "reviewer" })).toBe(false);
    expect(roleLabel({ token: "t", user: "rita", role: "reviewer" })).toBe("rita (reviewer, read-only)");
    expect(roleLabel(KIOSK)).toBe("Kiosk (full access)");
  });

  it("stores and loads the session; an expired or garbled one is dropped", () => {
    const st = memStore();
    const s = sessionFromLogin({ token: "abc", user: "sam", role: "surgeon", expires_utc: "2030-01-01T00:00:00Z" });
    saveSession(st, s);
    expect(loadSession(st, Date.parse("2029-12-31T00:00:00Z"))).toEqual(s);
    expect(loadSession(st, Date.parse("2030-01-01T00:00:01Z"))).toBeNull();
    expect(st.m.size).toBe(0); // the expired one was removed
    st.setItem("cortexfuse.session", "{not json");
    expect(loadSession(st)).toBeNull();
    saveSession(st, s);
    saveSession(st, null);
    expect(loadSession(st)).toBeNull();
  });

  it("puts the token on the WebSocket address, URL-encoded", () => {
    expect(wsUrl({ protocol: "http:", host: "10.0.0.2:8080" }, KIOSK)).toBe("ws://10.0.0.2:8080/api/ws");
    expect(wsUrl({ protocol: "https:", host: "h" }, { token: "a+b/c", user: "u", role: "reviewer" })).toBe("wss://h/api/ws?token=a%2Bb%2Fc");
  });
});
