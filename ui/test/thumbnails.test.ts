import { describe, expect, it } from "vitest";
import { ThumbnailLoader, thumbCaption } from "../src/thumbnails";

/** A fetch whose answers the test releases; records the paths asked. */
function heldFetch() {
  const calls: { path: string; release: (r: Response) => void }[] = [];
  const f = (path: string) => new Promise<Response>((resolve) => { calls.push({ path, release: resolve }); });
  return { f, calls };
}
const jpeg = (source: string, note?: string) => {
  const headers: Record<string, string> = { "Content-Type": "image/jpeg", "X-Thumbnail-Source": source };
  if (note) headers["X-Thumbnail-Note"] = note;
  return new Response(new Uint8Array([0xff, 0xd8, 0xff, 0xd9]), { status: 200, headers });
};
const refusal = (status: number, message: string) =>
  new Response(JSON.stringify({ error: { code: "not_found", status, message } }), { status });

describe("case thumbnails", () => {
  it("tells the fused view, the photo and the placeholder apart", async () => {
    const { f, calls } = heldFetch();
    let urls = 0;
    const loader = new ThumbnailLoader(f as unknown as typeof fetch, () => `blob:${++urls}`);
    const a = loader.get(1, "t1"), b = loader.get(2, "t1"), c = loader.get(3, "t1"), d = loader.get(4, "t1");
    await Promise.resolve();
    // Two at a time: the other two wait.
    expect(calls.map((x) => x.path)).toEqual(["/api/cases/1/thumbnail", "/api/cases/2/thumbnail"]);
    calls[0].release(jpeg("fused"));
    calls[1].release(jpeg("photo", "fused case 2: the camera points away from the brain"));
    expect(await a).toEqual({ source: "fused", url: "blob:1", note: "" });
    const tb = await b;
    expect(tb.source).toBe("photo");
    expect(thumbCaption(tb)).toBe("Photo (no fused view: see tooltip)");
    await new Promise((r) => setTimeout(r, 0));
    expect(calls).toHaveLength(4);
    calls[2].release(refusal(404, "case 3 thumbnail: no photo or fused view yet (add a photo, or register the case)"));
    calls[3].release(refusal(500, "case 4 thumbnail: photo 7 (p.png) does not decode"));
    const tc = await c, td = await d;
    expect(tc).toEqual({ source: "none", url: null, note: "No photo or fused view yet" });
    expect(thumbCaption(tc)).toBe("No photo or fused view yet");
    expect(td.source).toBe("error");
    expect(td.note).toContain("does not decode");
    expect(thumbCaption(await a)).toBe("Fused view");
  });

  it("asks again only when the case changed", async () => {
    let n = 0;
    const loader = new ThumbnailLoader((async () => { n++; return jpeg("photo"); }) as unknown as typeof fetch, () => "blob:x");
    await loader.get(5, "2026-11-23T10:00:00Z");
    await loader.get(5, "2026-11-23T10:00:00Z");
    expect(n).toBe(1);
    await loader.get(5, "2026-11-23T11:00:00Z");
    expect(n).toBe(2);
    expect(loader.inFlight).toBe(0);
  });
});
