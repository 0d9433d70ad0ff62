// JSON-RPC 2.0 over the daemon's WebSocket (/api/ws, docs/api/push.md): framing and the
// table of calls waiting for their answer. Hand-written: it is ~80 lines and the npm JSON-RPC
// clients bring their own transports we do not need.

export interface RpcErrorObject {
  code: number;
  message: string;
  data?: unknown;
}

export type Incoming =
  | { kind: "result"; id: number | string; result: unknown }
  | { kind: "error"; id: number | string | null; error: RpcErrorObject }
  | { kind: "notification"; method: string; params: unknown }
  | { kind: "invalid"; reason: string };

export function encodeRequest(id: number, method: string, params?: Record<string, unknown>): string {
  const msg: Record<string, unknown> = { jsonrpc: "2.0", id, method };
  if (params !== undefined) msg.params = params;
  return JSON.stringify(msg);
}

/** Classifies one text message from the daemon. Never throws. */
export function parseMessage(text: string): Incoming {
  let m: unknown;
  try {
    m = JSON.parse(text);
  } catch {
    return { kind: "invalid", reason: "not JSON" };
  }
  if (!m || typeof m !== "object" || Array.isArray(m)) return { kind: "invalid", reason: "not an object" };
  const o = m as Record<string, unknown>;
  if (o.jsonrpc !== "2.0") return { kind: "invalid", reason: "jsonrpc is not \"2.0\"" };
  if (typeof o.method === "string") {
    if ("id" in o && o.id !== null && o.id !== undefined) return { kind: "invalid", reason: "a request from the daemon" };
    return { kind: "notification", method: o.method, params: o.params ?? {} };
  }
  const idOk = typeof o.id === "number" || typeof o.id === "string";
  if ("error" in o) {
    const e = o.error as Record<string, unknown> | null;
    if (!e || typeof e !== "object" || typeof e.code !== "number" || typeof e.message !== "string")
      return { kind: "invalid", reason: "malformed error" };
    return { kind: "error", id: idOk ? (o.id as number | string) : null,
             error: { code: e.code, message: e.message, data: e.data } };
  }
  if ("result" in o && idOk) return { kind: "result", id: o.id as number | string, result: o.result };
  return { kind: "invalid", reason: "neither a result, an error nor a notification" };
}

export class RpcCallError extends Error {
  constructor(readonly code: number, message: string, readonly data?: unknown) {
    super(message);
    this.name = "RpcCallError";
  }
}

/** Calls waiting for answers over one connection; send() is the socket's. */
export class RpcSession {
  private nextId = 1;
  private pending = new Map<number | string, { resolve: (v: unknown) => void; reject: (e: Error) => void }>();

  constructor(
    private readonly sendText: (text: string) => void,
    private readonly onNotification: (method: string, params: unknown) => void,
  ) {}

  call<T = unknown>(method: string, params?: Record<string, unknown>): Promise<T> {
    const id = this.nextId++;
    return new Promise<T>((resolve, reject) => {
      this.pending.set(id, { resolve: resolve as (v: unknown) => void, reject });
      try {
        this.sendText(encodeRequest(id, method, params));
      } catch (e) {
        this.pending.delete(id);
        reject(e instanceof Error ? e : new Error(String(e)));
      }
    });
  }

  get waiting(): number {
    return this.pending.size;
  }

  /** Feeds one message; answers settle their call, notifications go to the handler. */
  handle(text: string): Incoming {
    const m = parseMessage(text);
    if (m.kind === "notification") this.onNotification(m.method, m.params);
    else if (m.kind === "result" || m.kind === "error") {
      const p = m.id === null ? undefined : this.pending.get(m.id);
      if (p && m.id !== null) {
        this.pending.delete(m.id);
        if (m.kind === "result") p.resolve(m.result);
        else p.reject(new RpcCallError(m.error.code, m.error.message, m.error.data));
      }
    }
    return m;
  }

  /** The connection closed: every waiting call fails with this reason. */
  failAll(reason: string): void {
    const all = [...this.pending.values()];
    this.pending.clear();
    for (const p of all) p.reject(new Error(reason));
  }
}
