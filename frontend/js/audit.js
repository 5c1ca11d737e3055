// The audit trail (admins): every state change asked for, newest first, filtered by user,
// run, time and action.

import { ApiError, get, setMode } from "./api.js";

const $ = (id) => document.getElementById(id);

function cell(row, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  row.append(td);
}

async function load() {
  const query = new URLSearchParams();
  if ($("f-user").value.trim()) query.set("user", $("f-user").value.trim());
  if ($("f-run").value) query.set("run", $("f-run").value);
  if ($("f-since").value) query.set("since", new Date($("f-since").value).toISOString());
  if ($("f-action").value.trim()) query.set("action", $("f-action").value.trim());
  const rows = await get(`/api/audit?${query}`);
  const body = $("audit-rows");
  body.replaceChildren();
  for (const r of rows) {
    const tr = document.createElement("tr");
    cell(tr, r.at.replace("T", " ").slice(0, 19));
    cell(tr, r.user);
    cell(tr, r.address);
    cell(tr, r.action);
    cell(tr, r.target);
    cell(tr, `${r.outcome} (${r.status})`, r.outcome);
    cell(tr, Object.entries(r.detail).map(([k, v]) => `${k}: ${v}`).join("; "));
    body.append(tr);
  }
}

async function show() {
  try {
    await load();
    $("message").hidden = true;
  } catch (err) {
    $("message").textContent = err instanceof ApiError ? `${err.message} (HTTP ${err.status})` : String(err);
    $("message").hidden = false;
  }
}

async function start() {
  const me = await get("/api/auth/whoami");
  setMode(me.mode);
  if (me.mode === "users" && !me.user) return location.assign("/login.html");
  $("filters").addEventListener("submit", (e) => {
    e.preventDefault();
    show();
  });
  await show();
}

start();
