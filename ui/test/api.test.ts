import { describe, expect, it } from "vitest";
import { ApiError, apiJson, apiRender, errorFromAnswer, plainMessage, type FetchLike } from "../src/api";

const answer = (status: number, body: string, headers: Record<string, string> = {}): FetchLike =>
  async () => new Response(body, { status, headers });

describe("api client", () => {
  it("returns the parsed JSON of a 2xx answer and sends the body as JSON", async () => {
    let seen: RequestInit | undefined;
    const f: FetchLike = async (_u, init) => { seen = init; return new Response('{"id":3,"title":"x"}', { status: 201 }); };
    const r = await apiJson<{ id: number }>("POST", "/api/cases", { title: "x" }, f);
    expect(r.id).toBe(3);
    expect(seen?.method).toBe("POST");
    expect(seen?.body).toBe('{"title":"x"}');
    expect((seen?.headers as Record<string, string>)["Content-Type"]).toBe("application/json");
  });

  it("turns the daemon's {error:{code,message}} into an ApiError with its words", async () => {
    const f = answer(400, '{"error":{"code":"bad_request","status":400,"message":"title: must not be empty"}}');
    const e: any = await apiJson("POST", "/api/cases", { title: "" }, f).catch((x: any) => x);
    expect(e).toBeInstanceOf(ApiError);
    expect(e.status).toBe(400);
    expect(e.code).toBe("bad_request");
    expect(plainMessage(e)).toBe("title: must not be empty");
  });

  it("explains an answer without a JSON error body in plain words", () => {
    const e = errorFromAnswer("GET", "/api/cases/9", 404, "<html>not found</html>");
    expect(e.code).toBe("http_404");
    expect(e.message).toBe("GET /api/cases/9: it does not exist (HTTP 404).");
    expect(errorFromAnswer("POST", "/api/render", 503, "").message).toContain("busy or not ready");
    expect(errorFromAnswer("GET", "/api/x", 500, '{"error":"x"}').message).toContain("the daemon failed (HTTP 500)");
  });

  it("says the daemon cannot be reached when fetch itself fails", async () => {
    const f: FetchLike = async () => { throw new TypeError("Failed to fetch"); };
    const e: any = await apiJson("GET", "/api/status", undefined, f).catch((x: any) => x);
    expect(e).toBeInstanceOf(ApiError);
    expect(e.status).toBe(0);
    expect(e.code).toBe("unreachable");
    expect(e.message).toMatch(/cannot be reached \(GET \/api\/status\)/);
  });

  it("refuses a 2xx answer that is not JSON", async () => {
    const e: any = await apiJson("GET", "/api/status", undefined, answer(200, "<html>")).catch((x: any) => x);
    expect(e.code).toBe("bad_answer");
  });

  it("reads the render headers and the image", async () => {
    const f = answer(200, "JPEGDATA", { "Content-Type": "image/jpeg", "X-Image-Size": "160x120", "X-Render-Ms": "12.5", "X-Renderer": "gl" });
    const r = await apiRender({ width: 160, height: 120 }, f);
    expect([r.width, r.height, r.renderMs, r.renderer]).toEqual([160, 120, 12.5, "gl"]);
    expect(await r.blob.text()).toBe("JPEGDATA");
    const bad: any = await apiRender({ preset: "nope" }, answer(400, '{"error":{"code":"bad_request","message":"preset: unknown"}}')).catch((x: any) => x);
    expect(bad.message).toBe("preset: unknown");
  });

  it("words other throwables", () => {
    expect(plainMessage(new Error("boom"))).toBe("Something went wrong: boom");
    expect(plainMessage("x")).toBe("Something went wrong: x");
  });
});

describe("api client with a login session", () => {
  it("sends the token as a bearer and reports a 401 to the session hook (not the login's own)", async () => {
    const { auth } = await import("../src/api");
    const seen: string[] = [];
    let hdr: Record<string, string> = {};
    auth.token = "tok123";
    auth.onUnauthorized = (e) => seen.push(e.message);
    try {
      const f: FetchLike = async (_u, init) => { hdr = init?.headers as Record<string, string>; return new Response('{"error":{"code":"unauthorized","message":"session expired"}}', { status: 401 }); };
      const e: any = await apiJson("GET", "/api/cases", undefined, f).catch((x: any) => x);
      expect(hdr["Authorization"]).toBe("Bearer tok123");
      expect(e.status).toBe(401);
      expect(seen).toEqual(["session expired"]);
      await apiJson("POST", "/api/login", { name: "a", password: "b" }, f).catch(() => {});
      expect(seen).toHaveLength(1);
      auth.token = null;
      await apiJson("GET", "/api/cases", undefined, f).catch(() => {});
      expect(hdr["Authorization"]).toBeUndefined();
    } finally {
      auth.token = null;
      auth.onUnauthorized = null;
    }
  });
});

describe("uploads and downloads", () => {
  it("sends a file's bytes as an octet stream and reads the JSON answer; a refusal names the file", async () => {
    const { apiUpload, apiBlob } = await import("../src/api");
    let seen: RequestInit | undefined;
    const ok: FetchLike = async (_u, init) => { seen = init; return new Response('{"id":4}', { status: 201 }); };
    const bytes = new Uint8Array([1, 2, 3]).buffer;
    expect(await apiUpload<{ id: number }>("/api/cases/1/photos?name=p.png", bytes, ok)).toEqual({ id: 4 });
    expect((seen?.headers as Record<string, string>)["Content-Type"]).toBe("application/octet-stream");
    expect(seen?.body).toBe(bytes);
    const bad: FetchLike = async () => new Response('{"error":{"code":"bad_request","message":"photo p.png: not a PNG (signature)"}}', { status: 400 });
    const e: any = await apiUpload("/api/cases/1/photos?name=p.png", bytes, bad).catch((x: any) => x);
    expect(e.message).toBe("photo p.png: not a PNG (signature)");
    const img: FetchLike = async () => new Response(new Uint8Array([9, 8]), { status: 200, headers: { "Content-Type": "image/png" } });
    expect((await apiBlob("/api/cases/1/photos/1", img)).size).toBe(2);
  });
});

describe("messages", () => {
  it("shows the UI's own checks as they are and anything else as something that went wrong", async () => {
    const { UserMessage } = await import("../src/api");
    expect(plainMessage(new UserMessage("Type a title for the new case first."))).toBe("Type a title for the new case first.");
    expect(plainMessage(new Error("boom"))).toBe("Something went wrong: boom");
  });
});
