// The REST API: JSON in and out, the bearer token on every change, errors as messages.

const TOKEN_KEY = "mosaic-afm-token";

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

export async function request(method, url, body) {
  const headers = {};
  const options = { method, headers };
  if (method !== "GET") {
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
