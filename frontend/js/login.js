// The users mode's login: the tokens go in HttpOnly cookies (the page's script never holds
// them); the CSRF token comes back as a cookie the page echoes on every change.

import { ApiError, get, post } from "./api.js";

const $ = (id) => document.getElementById(id);

async function start() {
  const me = await get("/api/auth/whoami").catch(() => null);
  if (me && me.mode === "single") $("single-mode").hidden = false;
  if (me && me.user) location.assign("/");
  $("login").addEventListener("submit", async (e) => {
    e.preventDefault();
    $("login-error").textContent = "";
    $("login-button").disabled = true;
    try {
      await post("/api/auth/login", { username: $("username").value.trim(), password: $("password").value, cookie: true });
      location.assign("/");
    } catch (err) {
      $("login-error").textContent = err instanceof ApiError ? err.message : String(err);
    } finally {
      $("login-button").disabled = false;
    }
  });
}

start();
