// The JSON API, with the reviewer's key. The key lives in this tab's sessionStorage and travels only in the
// Authorization header: never in a URL (where logs and history would keep it), never in a cookie.

const KEY = "precond.key";
let askForKey = null;

export class ApiError extends Error {
  constructor(status, body) {
    const error = (body && body.error) || {};
    super(error.message || `the service answered ${status}`);
    this.status = status;
    this.type = error.type;
    this.field = error.field;
    this.blocked = error.blocked || [];  // blocks_demonstration: every demonstrated call the new rules refuse
  }
}

/** `ask(message)` resolves to a key typed by the reviewer; called when the API answers 401. */
export function whenKeyNeeded(ask) { askForKey = ask; }
export function hasKey() { return sessionStorage.getItem(KEY) !== null; }
export function forgetKey() { sessionStorage.removeItem(KEY); }

export async function api(method, path, body) {
  for (let attempt = 0; ; attempt++) {
    const headers = { Accept: "application/json" };
    const key = sessionStorage.getItem(KEY);
    if (key) headers.Authorization = `Bearer ${key}`;
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const answer = await fetch(path, {
      method, headers, credentials: "omit", cache: "no-store",
      body: body === undefined ? undefined : JSON.stringify(body),
    });
    const data = await answer.json().catch(() => null);
    if (answer.status === 401 && askForKey && attempt < 5) {
      sessionStorage.setItem(KEY, await askForKey(data && data.error ? data.error.message : ""));
      continue;
    }
    if (!answer.ok) throw new ApiError(answer.status, data);
    return { status: answer.status, body: data, headers: answer.headers };
  }
}

const sleep = (ms) => new Promise((done) => setTimeout(done, ms));

/** The result of an operation: at once (200), or by polling its job (202), telling `progress` each time. */
export async function follow(answer, progress) {
  if (answer.status !== 202) return answer.body;
  const location = answer.headers.get("Location");
  for (;;) {
    await sleep(250);
    const job = (await api("GET", location)).body;
    if (progress) progress(job);
    if (job.status === "succeeded") return job.result;
    if (job.status === "failed" || job.status === "cancelled") {
      throw new ApiError(job.status === "cancelled" ? 409 : 422,
        { error: job.error || { message: `the job was ${job.status}` } });
    }
  }
}

export const setPath = (reference) => `/precondition-sets/${encodeURIComponent(reference)}`;
