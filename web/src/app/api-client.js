// The REST API as the app calls it: same-origin fetch with the session cookie, JSON in and out, and the service's
// error body ({message, problems}) raised as an ApiError. No DOM.

// Sent with every call: a cross-site form cannot set it, so a cookie-authenticated write must come from this app.
export const APP_HEADER = { "X-Panogs-App": "1" };

export class ApiError extends Error {
  constructor(status, body) {
    super(body.message || `HTTP ${status}`);
    this.status = status;
    this.problems = body.problems || [];
  }
}

// The parsed JSON answer (null for 204); anything but 2xx throws an ApiError. A body that is not JSON becomes the
// message.
export async function api(method, path, body) {
  const init = { method, credentials: "same-origin", headers: { ...APP_HEADER } };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  if (response.status === 204) return null;
  const text = await response.text();
  let parsed;
  try {
    parsed = text ? JSON.parse(text) : {};
  } catch (_) {
    parsed = { message: text };
  }
  if (!response.ok) throw new ApiError(response.status, parsed);
  return parsed;
}

// Who is signed in ({tenant}), or null.
export async function currentSession() {
  try {
    return await api("GET", "/app/session");
  } catch (err) {
    if (err.status === 401) return null;
    throw err;
  }
}

// A failed tus upload (tus-js-client's error, with the server's answer when there was one) as an ApiError, so the
// bundle's problems show like any other refusal.
export function tusError(err) {
  const response = err.originalResponse;
  let body = {};
  try {
    body = JSON.parse(response?.getBody() || "{}");
  } catch (_) {
    /* not JSON */
  }
  return new ApiError(response?.getStatus() || 0, {
    message: body.message || String(err.message || err),
    problems: body.problems,
  });
}
