// Who is at the page, and the operator lock: the users mode's header (name, log out, the
// audit page for admins) and the lock panel (who holds the instrument, take, release).

import { del, get, post, setMode } from "./api.js";

const $ = (id) => document.getElementById(id);
let me = null;

/** Ask the server who we are; in the users mode without a login, go to the login page.
 *  Returns whoami's answer, or null while the browser leaves for the login page. */
export async function startSession() {
  me = await get("/api/auth/whoami");
  setMode(me.mode);
  if (me.mode !== "users") {
    $("audit-link").hidden = false; // read with the API token
    return me;
  }
  if (!me.user && !me.anonymous_read) {
    location.assign("/login.html");
    return null;
  }
  $("token-label").hidden = true;
  $("who").hidden = false;
  $("who").textContent = me.user ? `${me.user} · ${me.role}` : "not logged in (reading)";
  $("logout").hidden = !me.user;
  $("audit-link").hidden = !me.scopes.includes("audit");
  $("logout").addEventListener("click", async () => {
    await post("/api/auth/logout");
    location.assign("/login.html");
  });
  $("lock-panel").hidden = false;
  const may = me.scopes.includes("instrument");
  $("lock-take").hidden = !may;
  $("lock-release").hidden = !may;
  $("lock-note").hidden = !may;
  return me;
}

/** Show who holds the instrument (called at start and on every "lock" event). */
export async function loadLock() {
  if (!me || me.mode !== "users") return;
  const lock = await get("/api/lock");
  const text = $("lock-state");
  if (!lock.held) {
    text.textContent = "Instrument free: nobody holds the lock";
    text.className = "pill ok";
  } else {
    const since = new Date(lock.since).toLocaleString();
    const note = lock.note ? ` — ${lock.note}` : "";
    text.textContent = lock.yours ? `You hold the instrument (since ${since})${note}` : `Held by ${lock.holder} since ${since}${note}`;
    text.className = `pill ${lock.yours ? "ok" : "busy"}`;
  }
  $("lock-take").disabled = lock.held && !lock.yours;
  $("lock-take").textContent = lock.yours ? "Change note" : "Take the instrument";
  $("lock-release").disabled = !lock.held || (!lock.yours && !me.scopes.includes("lock:break"));
  $("lock-release").textContent = lock.held && !lock.yours ? "Break the lock" : "Release";
}

export function wireLock(act) {
  $("lock-take").addEventListener("click", () => act(async () => {
    await post("/api/lock", { note: $("lock-note").value.trim() });
    await loadLock();
  }));
  $("lock-release").addEventListener("click", () => act(async () => {
    const breaking = $("lock-release").textContent === "Break the lock";
    const reason = breaking ? prompt("Why do you break another operator's lock? (logged)") : "";
    if (breaking && !reason) return;
    await del("/api/lock", breaking ? { reason } : undefined);
    await loadLock();
  }));
}
