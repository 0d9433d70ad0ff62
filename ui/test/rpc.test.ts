import { describe, expect, it } from "vitest";
import { encodeRequest, parseMessage, RpcCallError, RpcSession } from "../src/rpc";

describe("JSON-RPC framing", () => {
  it("encodes a request with and without params", () => {
    expect(JSON.parse(encodeRequest(7, "jobs.get", { id: "3" }))).toEqual({ jsonrpc: "2.0", id: 7, method: "jobs.get", params: { id: "3" } });
    expect(JSON.parse(encodeRequest(1, "status.get"))).toEqual({ jsonrpc: "2.0", id: 1, method: "status.get" });
  });

  it("classifies results, errors and notifications", () => {
    expect(parseMessage('{"jsonrpc":"2.0","id":1,"result":{"a":1}}')).toEqual({ kind: "result", id: 1, result: { a: 1 } });
    expect(parseMessage('{"jsonrpc":"2.0","id":2,"result":null}')).toEqual({ kind: "result", id: 2, result: null });
    expect(parseMessage('{"jsonrpc":"2.0","id":3,"error":{"code":404,"message":"job 9 not found","data":{"code":"not_found"}}}'))
      .toEqual({ kind: "error", id: 3, error: { code: 404, message: "job 9 not found", data: { code: "not_found" } } });
    expect(parseMessage('{"jsonrpc":"2.0","id":null,"error":{"code":-32700,"message":"parse error"}}'))
      .toMatchObject({ kind: "error", id: null });
    expect(parseMessage('{"jsonrpc":"2.0","method":"notify_status","params":{"uptime_s":3}}'))
      .toEqual({ kind: "notification", method: "notify_status", params: { uptime_s: 3 } });
  });

  it("rejects what is not JSON-RPC 2.0", () => {
    for (const t of ["not json", "[1,2]", "null", '{"id":1,"result":1}', '{"jsonrpc":"1.0","id":1,"result":1}',
                     '{"jsonrpc":"2.0","id":1,"error":{"code":"x"}}', '{"jsonrpc":"2.0","id":1}', '{"jsonrpc":"2.0","id":5,"method":"x"}'])
      expect(parseMessage(t).kind, t).toBe("invalid");
  });
});

describe("RpcSession", () => {
  it("matches answers to calls by id, in any order, and passes notifications on", async () => {
    const sent: string[] = [];
    const notes: [string, unknown][] = [];
    const s = new RpcSession((t) => sent.push(t), (m, p) => notes.push([m, p]));
    const a = s.call("status.get");
    const b = s.call("jobs.get", { id: "1" });
    expect(sent.map((t) => JSON.parse(t).id)).toEqual([1, 2]);
    s.handle('{"jsonrpc":"2.0","method":"notify_job","params":{"id":1}}');
    s.handle('{"jsonrpc":"2.0","id":2,"error":{"code":404,"message":"job 1 not found"}}');
    s.handle('{"jsonrpc":"2.0","id":1,"result":{"ok":true}}');
    await expect(a).resolves.toEqual({ ok: true });
    const e: any = await b.catch((x: any) => x);
    expect(e).toBeInstanceOf(RpcCallError);
    expect([e.code, e.message]).toEqual([404, "job 1 not found"]);
    expect(notes).toEqual([["notify_job", { id: 1 }]]);
    expect(s.waiting).toBe(0);
  });

  it("ignores answers to unknown ids and fails every waiting call when the socket closes", async () => {
    const s = new RpcSession(() => {}, () => {});
    const a = s.call("status.get");
    s.handle('{"jsonrpc":"2.0","id":99,"result":1}');
    expect(s.waiting).toBe(1);
    s.failAll("the push channel closed");
    await expect(a).rejects.toThrow("the push channel closed");
    expect(s.waiting).toBe(0);
  });

  it("rejects a call whose send throws and forgets it", async () => {
    const s = new RpcSession(() => { throw new Error("socket not open"); }, () => {});
    await expect(s.call("x")).rejects.toThrow("socket not open");
    expect(s.waiting).toBe(0);
  });
});
