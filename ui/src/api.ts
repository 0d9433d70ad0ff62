// The daemon's HTTP API: JSON requests, errors turned into one plain-words line.
// The daemon answers failures as {"error": {"code", "status", "message"}} (docs/api/*.md).

export class ApiError extends Error {
  constructor(
    readonly status: number, // HTTP status; 0 when the daemon could not be reached
    readonly code: string, // the daemon's error code ("not_found", ...) or "unreachable" / "bad_answer"
    message: string,
  ) {
    super(message);
    this.name = "ApiError";
  }
}

export type FetchLike = (input: string, init?: RequestInit) => Promise<Response>;

/** The login session the requests carry (docs/api/cases.md): `token` is sent as
 *  `Authorization: Bearer`; `onUnauthorized` hears every 401 except the login's own (an
 *  expired or missing session: the UI shows its login screen). */
export const auth: { token: string | null; onUnauthorized: ((e: ApiError) => void) | null } = { token: null, onUnauthorized: null };

function what(method: string, path: string): string {
  return `${method} ${path}`;
}

/** Builds the ApiError for a non-2xx answer from its status and body text. */
export function errorFromAnswer(method: string, path: string, status: number, bodyText: string): ApiError {
  let code = `http_${status}`;
  let message = "";
  try {
    const j = JSON.parse(bodyText) as { error?: { code?: unknown; message?: unknown } };
    if (j && typeof j === "object" && j.error && typeof j.error === "object") {
      if (typeof j.error.code === "string") code = j.error.code;
      if (typeof j.error.message === "string") message = j.error.message;
    }
  } catch {
    /* not JSON: the plain fallback below */
  }
  if (!message) {
    const reason =
      status === 401 ? "a login is needed" :
      status === 403 ? "this user may not do that" :
      status === 404 ? "it does not exist" :
      status === 413 ? "the request is too large" :
      status === 503 ? "the daemon is busy or not ready" :
      status >= 500 ? "the daemon failed" : "the request was refused";
    message = `${what(method, path)}: ${reason} (HTTP ${status}).`;
  }
  return new ApiError(status, code, message);
}

async function send(fetchImpl: FetchLike, method: string, path: string, body?: unknown, raw?: Blob | ArrayBuffer): Promise<Response> {
  const init: RequestInit = { method, headers: {} };
  if (auth.token) (init.headers as Record<string, string>)["Authorization"] = `Bearer ${auth.token}`;
  if (raw !== undefined) {
    init.body = raw;
    (init.headers as Record<string, string>)["Content-Type"] = "application/octet-stream";
  } else if (body !== undefined) {
    init.body = JSON.stringify(body);
    (init.headers as Record<string, string>)["Content-Type"] = "application/json";
  }
  let res: Response;
  try {
    res = await fetchImpl(path, init);
  } catch (e) {
    if (e instanceof DOMException && e.name === "AbortError") throw e;
    throw new ApiError(0, "unreachable",
      `The daemon cannot be reached (${what(method, path)}). Check that cortexfused is running; the screen retries on its own.`);
  }
  if (!res.ok) {
    const e = errorFromAnswer(method, path, res.status, await res.text().catch(() => ""));
    if (e.status === 401 && path !== "/api/login") auth.onUnauthorized?.(e);
    throw e;
  }
  return res;
}

/** A JSON request; resolves to the parsed answer, rejects with an ApiError. */
export async function apiJson<T>(method: string, path: string, body?: unknown, fetchImpl: FetchLike = fetch): Promise<T> {
  const res = await send(fetchImpl, method, path, body);
  const text = await res.text();
  try {
    return JSON.parse(text) as T;
  } catch {
    throw new ApiError(res.status, "bad_answer", `${what(method, path)}: the daemon's answer is not JSON.`);
  }
}

/** Uploads a file's bytes as the body (the case data endpoints); resolves to the JSON answer. */
export async function apiUpload<T>(path: string, bytes: Blob | ArrayBuffer, fetchImpl: FetchLike = fetch): Promise<T> {
  const res = await send(fetchImpl, "POST", path, undefined, bytes);
  const text = await res.text();
  try {
    return JSON.parse(text) as T;
  } catch {
    throw new ApiError(res.status, "bad_answer", `POST ${path}: the daemon's answer is not JSON.`);
  }
}

/** GET of a file (a photo, a result) as a Blob, with the session's token (an <img src> could not send it). */
export async function apiBlob(path: string, fetchImpl: FetchLike = fetch, method = "GET"): Promise<Blob> {
  return (await send(fetchImpl, method, path)).blob();
}

/** POST a JSON body and answer the image (e.g. POST /api/cases/N/fused). */
export async function apiPostBlob(path: string, body: unknown, fetchImpl: FetchLike = fetch): Promise<Blob> {
  return (await send(fetchImpl, "POST", path, body)).blob();
}

export interface RenderedImage {
  blob: Blob;
  width: number;
  height: number;
  renderMs: number;
  renderer: string;
}

/** POST /api/render: resolves to the image and its headers. */
export async function apiRender(body: Record<string, unknown>, fetchImpl: FetchLike = fetch): Promise<RenderedImage> {
  const res = await send(fetchImpl, "POST", "/api/render", body);
  const size = (res.headers.get("X-Image-Size") ?? "").split("x").map(Number);
  return {
    blob: await res.blob(),
    width: size[0] || Number(body.width) || 0,
    height: size[1] || Number(body.height) || 0,
    renderMs: Number(res.headers.get("X-Render-Ms") ?? NaN),
    renderer: res.headers.get("X-Renderer") ?? "",
  };
}

/** A message for the user written by the UI itself (a check before a request): shown as it is. */
export class UserMessage extends Error {
  constructor(message: string) {
    super(message);
    this.name = "UserMessage";
  }
}

/** One line for an error banner, whatever was thrown. */
export function plainMessage(e: unknown): string {
  if (e instanceof ApiError || e instanceof UserMessage) return e.message;
  if (e instanceof Error) return `Something went wrong: ${e.message}`;
  return `Something went wrong: ${String(e)}`;
}
