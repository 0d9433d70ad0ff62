// The WebSocket push channel: connects to /api/ws, subscribes, hands notifications on,
// reconnects after a drop (1 s, then up to 5 s between tries).
import { RpcSession } from "./rpc";

export type PushState = "connecting" | "open" | "closed";

export class PushChannel {
  private ws: WebSocket | null = null;
  private session: RpcSession | null = null;
  private retryMs = 1000;
  private stopped = false;

  constructor(
    private readonly url: string,
    private readonly onNotify: (method: string, params: unknown) => void,
    private readonly onState: (s: PushState) => void,
  ) {}

  start(): void {
    this.stopped = false;
    this.connect();
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
      session.call("push.subscribe", { tracker_hz: 10, topics: ["tracker", "jobs", "status"] }).catch(() => {});
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") session.handle(ev.data);
    };
    ws.onclose = () => {
      session.failAll("the push channel closed");
      this.onState("closed");
      if (!this.stopped) {
        setTimeout(() => this.connect(), this.retryMs);
        this.retryMs = Math.min(5000, this.retryMs * 2);
      }
    };
  }
}
