// The WebSocket push channel: connects to /api/ws, subscribes, hands notifications on,
// reconnects after a drop (1 s, then up to 5 s between tries).
import { RpcSession } from "./rpc";

export type PushState = "connecting" | "open" | "closed";

export class PushChannel {
  private ws: WebSocket | null = null;
  private session: RpcSession | null = null;
  private retryMs = 1000;
  private stopped = false;
  private retryTimer: ReturnType<typeof setTimeout> | null = null;

  constructor(
    private readonly url: string,
    private readonly onNotify: (method: string, params: unknown) => void,
    private readonly onState: (s: PushState) => void,
    private readonly onError: (e: Error) => void = () => {},
  ) {}

  start(): void {
    this.stopped = false;
    this.connect();
  }

  /** Closes the socket for good (a new login opens a new channel with its token). */
  stop(): void {
    this.stopped = true;
    if (this.retryTimer !== null) { clearTimeout(this.retryTimer); this.retryTimer = null; }
    this.ws?.close();
  }

  call<T>(method: string, params?: Record<string, unknown>): Promise<T> {
    if (!this.session || this.ws?.readyState !== WebSocket.OPEN) return Promise.reject(new Error("push channel not open"));
    return this.session.call<T>(method, params);
  }

  private connect(): void {
    this.onState("connecting");
    const ws = new WebSocket(this.url);
    this.ws = ws;
    const session = new RpcSession((t) => ws.send(t), this.onNotify);
    this.session = session;
    ws.onopen = () => {
      this.retryMs = 1000;
      this.onState("open");
      session.call("push.subscribe", { tracker_hz: 10, topics: ["tracker", "jobs", "status"] }).catch((e: unknown) => {
        // A refused subscription leaves the status bar without live figures: say so (a closed
        // socket is already on the link banner).
        if (ws.readyState === WebSocket.OPEN) this.onError(new Error(`the live updates could not be subscribed (${e instanceof Error ? e.message : String(e)})`));
      });
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") session.handle(ev.data);
    };
    ws.onclose = () => {
      session.failAll("the push channel closed");
      if (this.stopped) return;
      this.onState("closed");
      if (!this.stopped) {
        this.retryTimer = setTimeout(() => { this.retryTimer = null; this.connect(); }, this.retryMs);
        this.retryMs = Math.min(5000, this.retryMs * 2);
      }
    };
  }
}
