// The REST API: JSON in and out, errors as messages. Single-user mode: the bearer token on
// every change. Users mode: the login's HttpOnly cookie goes by itself, every change carries
// the CSRF header, and an expired access token is refreshed once before the page gives up.

const TOKEN_KEY = "mosaic-afm-token";
// unknown until /api/auth/whoami answers: no credential is sent before (a single-mode token
// left in this browser would otherwise hide a users-mode login's cookie)
let mode = null;

/** The server's mode, from /api/auth/whoami: "single" or "users". */
export function setMode(value) {
  mode = value;
}

function cookie(name) {
  const found = document.cookie.split("; ").find((c) => c.startsWith(`${name}=`));
  return found ? decodeURIComponent(found.slice(name.length + 1)) : "";
}

/** A new access cookie from the refresh cookie; false when the session has ended. */
export async function refreshSession() {
  if (mode !== "users") return true;
  const r = await fetch("/api/auth/refresh", { method: "POST", headers: { "X-CSRF-Token": cookie("mosaic_csrf") } });
  return r.ok;
}

export function token() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

export function setToken(value) {
  localStorage.setItem(TOKEN_KEY, value.trim());
}

/** An error the server explained: `message` is its `detail` in words, `field` what to fix. */
export class ApiError extends Error {
  constructor(status, detail, field) {
    super(describe(detail));
    this.status = status;
    this.field = field || fieldOf(detail);
  }
}

function describe(detail) {
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((e) => `${(e.loc || []).filter((p) => p !== "body").join(".")}: ${e.msg}`).join("; ");
  }
  return JSON.stringify(detail);
}

function fieldOf(detail) {
  if (Array.isArray(detail) && detail[0] && detail[0].loc) {
    return detail[0].loc.filter((p) => p !== "body").join(".");
  }
  return null;
}

export async function request(method, url, body, retried = false) {
  const headers = {};
  const options = { method, headers };
  if (mode === "users") {
    if (method !== "GET") headers["X-CSRF-Token"] = cookie("mosaic_csrf");
  } else if (mode === "single" && (method !== "GET" || token())) {
    // reads are open in the single mode; the token lets this browser read the audit trail
    headers.Authorization = `Bearer ${token()}`;
    headers["X-Operator"] = "browser";
  }
  if (body instanceof FormData) {
    options.body = body;
  } else if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(url, options);
  } catch (err) {
    throw new ApiError(0, `the server did not answer (${err.message})`);
  }
  if (response.status === 401 && mode === "users" && !retried && !url.startsWith("/api/auth/")) {
    if (await refreshSession()) return request(method, url, body, true);
    location.assign("/login.html");
  }
  if (response.status === 204) return null;
  const text = await response.text();
  let data = null;
  try {
    data = text ? JSON.parse(text) : null;
  } catch {
    data = { detail: text };
  }
  if (!response.ok) {
    throw new ApiError(response.status, data && data.detail ? data.detail : response.statusText, data && data.field);
  }
  return data;
}

export const get = (url) => request("GET", url);
export const post = (url, body) => request("POST", url, body);
export const del = (url, body) => request("DELETE", url, body);
