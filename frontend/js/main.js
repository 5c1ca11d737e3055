// The operator's page: SEM and ROI, run control, patches, merge, instrument, 3D viewer.
// Live updates come from the server's event stream (/api/events), never from polling.

import { ApiError, get, post, refreshSession, setToken, token } from "./api.js";
import { duration, nm, um } from "./format.js";
import { buildPatchGrid, markQuality, showPatch } from "./patches.js";
import { plotProfile, plotResiduals } from "./plot.js";
import { SemView } from "./sem.js";
import { loadLock, startSession, wireLock } from "./session.js";

const $ = (id) => document.getElementById(id);
const state = { run: null, job: null, residuals: [], startedAt: null, lastEvent: 0 };

// -- messages ---------------------------------------------------------------------------------

function showError(err) {
  const box = $("message");
  box.textContent = err instanceof ApiError ? `${err.message} (HTTP ${err.status})` : String(err);
  box.hidden = false;
}

function clearError() {
  $("message").hidden = true;
}

/** Run `fn`, showing its failure on the page (background work: an earlier message stays). */
async function act(fn) {
  try {
    return await fn();
  } catch (err) {
    showError(err);
    return null;
  }
}

/** An operator's action: a new attempt clears the last message first. */
function userAct(fn) {
  clearError();
  return act(fn);
}

// -- SEM and planning -------------------------------------------------------------------------

const sem = new SemView($("sem-canvas"), $("sem-coords"), (rect) => roiDrawn(rect));
sem.draw();
let typedRoi = false; // the ROI fields were typed in: plan from them, not from the drawing

function roiDrawn(rect) {
  const f = $("plan-form").elements;
  if (!rect && typedRoi) {
    planPreview(); // a new image or Esc: a typed ROI stays
    return;
  }
  typedRoi = false;
  if (rect) {
    // the stage-aligned rectangle around the one drawn (turned, on a rotated image)
    const corners = [
      [rect.col, rect.row],
      [rect.col + rect.width, rect.row],
      [rect.col, rect.row + rect.height],
      [rect.col + rect.width, rect.row + rect.height],
    ].map(([c, r]) => sem.toStage(c, r));
    const xs = corners.map((p) => p.x);
    const ys = corners.map((p) => p.y);
    f.roi_x.value = (Math.min(...xs) * 1e6).toFixed(3);
    f.roi_y.value = (Math.min(...ys) * 1e6).toFixed(3);
    f.roi_width.value = ((Math.max(...xs) - Math.min(...xs)) * 1e6).toFixed(3);
    f.roi_height.value = ((Math.max(...ys) - Math.min(...ys)) * 1e6).toFixed(3);
  } else {
    for (const name of ["roi_x", "roi_y", "roi_width", "roi_height"]) f[name].value = "";
  }
  planPreview();
}

function hasRoi() {
  const f = $("plan-form").elements;
  return typedRoi ? f.roi_width.value !== "" && f.roi_height.value !== "" : Boolean(sem.roi);
}

function planBody() {
  const f = $("plan-form").elements;
  const num = (name) => Number(f[name].value);
  const roi = typedRoi
    ? { x: num("roi_x") * 1e-6, y: num("roi_y") * 1e-6, width: num("roi_width") * 1e-6, height: num("roi_height") * 1e-6 }
    : undefined;
  return {
    roi,
    sem_roi: !typedRoi && sem.roi && sem.image ? { sem_id: sem.image.meta.id, ...sem.roi } : undefined,
    patch: {
      width: num("patch_width") * 1e-6,
      height: num("patch_height") * 1e-6,
      pixels: [num("nx"), num("ny")],
    },
    overlap: [num("ox") / 100, num("oy") / 100],
    line_rate: num("line_rate"),
  };
}

const FIELD_INPUTS = {
  roi: "roi_width",
  "patch.width": "patch_width",
  "patch.height": "patch_height",
  "patch.pixels": "nx",
  overlap: "ox",
  line_rate: "line_rate",
};

function markInvalid(field) {
  for (const input of $("plan-form").querySelectorAll("input")) input.removeAttribute("aria-invalid");
  const key = field && Object.keys(FIELD_INPUTS).find((k) => field.startsWith(k));
  if (key) $("plan-form").elements[FIELD_INPUTS[key]].setAttribute("aria-invalid", "true");
}

// Previews overlap while the operator types or draws; only the newest request's answer counts,
// so a slow answer to an older form never re-enables "create run" over a newer refusal.
let planRequest = 0;

async function planPreview() {
  const request = ++planRequest;
  $("plan-error").textContent = "";
  markInvalid(null);
  if (!hasRoi()) {
    sem.setPlan(null);
    $("plan-summary").textContent = "draw an ROI on the SEM image";
    $("create-run").disabled = true;
    return;
  }
  const body = planBody();
  try {
    const plan = await post("/api/runs/preview", body);
    if (request !== planRequest) return;
    sem.setPlan({ ...plan, patchWidth: body.patch.width, patchHeight: body.patch.height });
    $("plan-summary").textContent = `${plan.count} patches (${plan.rows} rows × ${plan.cols} columns), ROI ${um(plan.roi.width)} × ${um(plan.roi.height)}`;
    $("plan-summary").dataset.count = plan.count;
    $("create-run").disabled = false;
  } catch (err) {
    if (request !== planRequest) return;
    sem.setPlan(null);
    $("plan-summary").textContent = "";
    $("plan-error").textContent = err.message;
    markInvalid(err.field);
    $("create-run").disabled = true;
  }
}

$("plan-form").addEventListener("input", (e) => {
  if (e.target.name && e.target.name.startsWith("roi_")) typedRoi = true;
  planPreview();
});
$("plan-form").addEventListener("submit", (e) => {
  e.preventDefault();
  userAct(async () => {
    const run = await post("/api/runs", planBody());
    await refreshRuns(run.id);
  });
});

$("sem-acquire").addEventListener("click", () =>
  userAct(async () => {
    // in line from the click: an older image arriving while the SEM acquires is not shown
    const ticket = sem.claim();
    const field = Number($("sem-field").value) * 1e-6;
    const meta = await post("/api/sem/acquire", { centre: [0, 0], field, pixels: 512 });
    await sem.load(meta, ticket);
  }),
);

/** The SEM-to-stage calibration in force, in words (or why there is none). */
function calibrationText(c) {
  if (!c) return "SEM calibration: none — acquired images are placed by the SEM's nominal pixel size and scan rotation";
  const when = new Date(c.created_at).toLocaleString();
  return (
    `SEM calibration #${c.id} (${when}, ${c.actor}, ${um(c.field)} field): ` +
    `${c.rotation_deg.toFixed(3)}°, ${nm(c.scale[0])} × ${nm(c.scale[1])} a pixel, ` +
    `shear ${c.shear.toFixed(4)}, residual ${c.residual_px.toFixed(2)} px`
  );
}

async function loadCalibration() {
  const all = await get("/api/sem/calibrations"); // newest, the one in force, first
  $("sem-calibration").textContent = calibrationText(all[0]);
}

$("sem-calibrate").addEventListener("click", () =>
  userAct(async () => {
    const field = Number($("sem-field").value) * 1e-6;
    $("sem-calibrate").disabled = true;
    $("sem-calibration").textContent = "SEM calibration: measuring (the sample stage moves; the tip stays withdrawn) …";
    try {
      const found = await post("/api/sem/calibrate", { field, pixels: 256 });
      $("sem-calibration").textContent = calibrationText(found);
    } catch (err) {
      await act(loadCalibration);
      throw err;
    } finally {
      $("sem-calibrate").disabled = false;
    }
  }),
);

$("sem-upload").addEventListener("change", (e) =>
  userAct(async () => {
    const file = e.target.files[0];
    if (!file) return;
    const form = new FormData();
    form.append("file", file);
    const pixel = Number($("sem-pixel").value);
    if (pixel > 0) form.append("pixel_size", String(pixel * 1e-9));
    const ticket = sem.claim(); // as for an acquired image: in line from the choice
    const meta = await post("/api/sem/upload", form);
    await sem.load(meta, ticket);
  }),
);

// -- runs -------------------------------------------------------------------------------------

const ACTIONS = {
  "run-start": { url: "start", when: ["planned", "failed", "interrupted"] },
  "run-pause": { url: "pause", when: ["running"] },
  "run-resume": { url: "resume", when: ["paused", "failed", "interrupted"] },
  "run-abort": { url: "abort", when: ["planned", "running", "paused", "failed", "interrupted"] },
  "run-reset": { url: "reset", when: ["fault"] },
};

for (const [id, action] of Object.entries(ACTIONS)) {
  $(id).addEventListener("click", () =>
    userAct(async () => {
      if (!state.run) return;
      let body;
      if (action.url === "abort") {
        if (!window.confirm(`Abort run ${state.run.id}? The tip is retracted and the run cannot continue.`)) return;
        body = { reason: "aborted from the operator's page" };
      }
      if (action.url === "reset") {
        const note = window.prompt(
          `Run ${state.run.id} is in fault: ${state.run.message}\nWhat did you check? (e.g. "tip inspected in the SEM: intact")`,
        );
        if (!note || note.trim().length < 3) return;
        body = { note: note.trim(), tip_changed: window.confirm("Was a new tip mounted?") };
      }
      await post(`/api/runs/${state.run.id}/${action.url}`, body);
      await loadRun(state.run.id);
    }),
  );
}

async function refreshRuns(select) {
  const runs = await get("/api/runs");
  const box = $("run-select");
  box.replaceChildren(new Option("—", ""));
  for (const r of runs) box.add(new Option(`run ${r.id} (${r.state}, ${r.rows}×${r.cols})`, r.id));
  const id = select ?? (runs[0] && runs[0].id);
  if (id) {
    box.value = String(id);
    await loadRun(id);
  }
}

$("run-select").addEventListener("change", (e) => userAct(() => (e.target.value ? loadRun(Number(e.target.value)) : null)));

async function loadRun(id) {
  const run = await get(`/api/runs/${id}`);
  const fresh = !state.run || state.run.id !== run.id;
  state.run = run;
  if (fresh) {
    buildPatchGrid($("patch-grid"), run);
    state.startedAt = null;
    await showLastMerge(run.id);
  }
  for (const p of run.patches) {
    markQuality($("patch-grid"), p.index, p.quality, p.reason);
    if (p.step === "stored") showPatch($("patch-grid"), run.id, p.index, act);
  }
  renderRun();
  $("merge-start").disabled = run.progress.stored < 2;
}

function renderRun() {
  const run = state.run;
  const pill = $("run-state");
  const option = [...$("run-select").options].find((o) => o.value === String(run.id));
  if (option) option.textContent = `run ${run.id} (${run.state}, ${run.rows}×${run.cols})`;
  pill.textContent = `run ${run.id}: ${run.state}${run.pending_request ? ` (${run.pending_request} asked)` : ""}`;
  pill.className = `pill ${{ running: "busy", paused: "busy", completed: "ok", fault: "bad", failed: "bad" }[run.state] || ""}`;
  for (const [id, action] of Object.entries(ACTIONS)) $(id).disabled = !action.when.includes(run.state);
  const { stored, total } = run.progress;
  $("run-progress").max = total;
  $("run-progress").value = stored;
  $("run-stored").textContent = `${stored} / ${total}`;
  $("run-patch").textContent = run.current_patch ?? "—";
  $("run-step").textContent = run.current_step ?? (run.state === "running" ? "between steps" : "—");
  $("run-message").textContent = run.message || "";
  const drawn = run.sem;
  $("run-sem").textContent = !drawn
    ? "stage coordinates"
    : `SEM image ${drawn.sem_id}, ` +
      (drawn.calibration_id
        ? `calibration #${drawn.calibration_id} (${drawn.rotation_deg.toFixed(3)}°, residual ${drawn.residual_px.toFixed(2)} px)`
        : "placed without a calibration (its metadata or nominal pixel)");
  if (run.state === "running" && !state.startedAt) state.startedAt = { t: Date.now(), stored };
  tick();
}

function tick() {
  const run = state.run;
  if (!run || !state.startedAt) {
    $("run-elapsed").textContent = "—";
    $("run-eta").textContent = "—";
    return;
  }
  const elapsed = (Date.now() - state.startedAt.t) / 1000;
  const done = run.progress.stored - state.startedAt.stored;
  const left = run.progress.total - run.progress.stored;
  $("run-elapsed").textContent = duration(elapsed);
  $("run-eta").textContent = run.state === "running" && done > 0 ? duration((elapsed / done) * left) : left ? "—" : "done";
}
setInterval(tick, 1000); // a clock on the page, not a request

$("offline-form").addEventListener("submit", (e) => {
  e.preventDefault();
  userAct(async () => {
    const f = $("offline-form").elements;
    const form = new FormData();
    for (const file of f.files.files) form.append("files", file);
    if (f.rows.value) form.append("rows", f.rows.value);
    if (f.cols.value) form.append("cols", f.cols.value);
    form.append("overlap_x", String(Number(f.overlap_x.value) / 100));
    form.append("overlap_y", String(Number(f.overlap_y.value) / 100));
    if (Number(f.pixel.value) > 0) form.append("pixel_size", String(Number(f.pixel.value) * 1e-9));
    const run = await post("/api/runs/offline", form);
    await refreshRuns(run.id);
  });
});

// -- patches ----------------------------------------------------------------------------------

// -- merges -----------------------------------------------------------------------------------

$("merge-form").addEventListener("submit", (e) => {
  e.preventDefault();
  $("merge-error").textContent = "";
  userAct(async () => {
    if (!state.run) return;
    const f = $("merge-form").elements;
    const parameters = f.max_iter.value ? { max_iter: Number(f.max_iter.value) } : {};
    try {
      const job = await post(`/api/runs/${state.run.id}/merges`, { method: f.method.value, parameters });
      // its events may have come first: then the page already follows this job
      if (!state.job || state.job.id !== job.id) startMerge(job);
    } catch (err) {
      $("merge-error").textContent = err.message;
      throw err;
    }
  });
});

$("merge-cancel").addEventListener("click", () =>
  userAct(async () => {
    if (state.job) renderMerge(await post(`/api/merges/${state.job.id}/cancel`));
  }),
);

/** A run opened (the page loaded, or another run chosen) shows its latest merge, with that
 * merge's registration and overlay: a reload loses nothing the server holds. */
async function showLastMerge(runId) {
  const jobs = await get(`/api/runs/${runId}/merges`);
  const last = jobs.reduce((a, b) => (!a || b.id > a.id ? b : a), null);
  if (state.run?.id !== runId) return; // another run was opened meanwhile
  state.job = null;
  state.residuals = [];
  $("merge-result").hidden = true;
  $("merge-error").textContent = "";
  if (last) renderMerge(last);
  else {
    $("merge-state").textContent = "no merge";
    $("merge-state").className = "pill";
    $("merge-progress").value = 0;
    $("merge-cancel").disabled = true;
  }
}

function startMerge(job) {
  state.job = job;
  state.residuals = [];
  $("merge-result").hidden = true;
  renderMerge(job);
}

function renderMerge(job) {
  state.job = { ...state.job, ...job };
  const j = state.job;
  $("merge-state").textContent = `merge ${j.id}: ${j.state}`;
  $("merge-state").className = `pill ${{ running: "busy", queued: "busy", done: "ok", failed: "bad" }[j.state] || ""}`;
  $("merge-progress").value = j.progress ?? 0;
  $("merge-cancel").disabled = !["queued", "running"].includes(j.state);
  if (j.state === "failed") $("merge-error").textContent = j.message || "the merge failed";
  if (j.state === "done") {
    $("merge-preview").src = `/api/merges/${j.id}/preview.png?size=480`;
    $("dl-npy").href = `/api/merges/${j.id}/mosaic.npy`;
    $("dl-json").href = `/api/merges/${j.id}/mosaic.json`;
    $("merge-result").hidden = false;
    act(async () => {
      const done = await get(`/api/merges/${j.id}/sem-registrations`); // the last first
      if (done.length) return showRegistration(done[0]);
      $("registration").textContent = "";
      $("overlay-box").hidden = true;
      $("apply-registration").hidden = true;
    });
  }
  plotResiduals($("residual-plot"), state.residuals);
}

// -- the mosaic on the SEM image ------------------------------------------------------------

function registrationText(r) {
  const t = r.transform;
  const placed = `${t.rotation_deg.toFixed(3)}° ± ${r.sigma.rotation_deg.toFixed(3)}, scale ${t.scale.toFixed(4)}, score ${r.score.toFixed(2)}`;
  if (!r.accepted) return `Not registered on SEM image ${r.sem_id}: ${r.reason} (${placed})`;
  const check = r.calibration
    ? ` The calibration #${r.calibration.id} that placed the image is off by ${r.calibration.displacement_px.toFixed(2)} px here (its stated uncertainty, k = 2: ${r.calibration.stated_px.toFixed(2)} px).`
    : " The image was placed without a calibration.";
  return `Registered on SEM image ${r.sem_id}: ${placed}, the mosaic's centre ± ${nm(r.sigma.centre)}.${check}`;
}

function showOverlay() {
  const opacity = $("overlay-blink").checked ? state.blinkOn ? 1 : 0 : Number($("overlay-opacity").value);
  $("sem-overlay").src = `/api/merges/${state.job.id}/sem-overlay.png?opacity=${opacity}&v=${state.registration}`;
}

function showRegistration(r) {
  state.registration = r.id;
  $("registration").textContent = registrationText(r);
  $("apply-registration").hidden = !(r.accepted && r.calibration);
  $("overlay-box").hidden = !r.accepted;
  state.overlayFrame = null;
  $("profile-plot").hidden = true;
  clearLine();
  if (r.accepted) showOverlay();
}

// a profile line dragged across the overlay: the picture's pixels go to mosaic coordinates
// by the map the server states for it, and the server cuts heights and SEM signal along it

function clearLine() {
  const c = $("profile-line");
  c.getContext("2d").clearRect(0, 0, c.width, c.height);
}

function drawLine(a, b) {
  const c = $("profile-line");
  c.width = c.clientWidth;
  c.height = c.clientHeight;
  const ctx = c.getContext("2d");
  for (const [colour, w] of [["#fff", 3], ["#c00", 1.5]]) {
    ctx.strokeStyle = colour;
    ctx.lineWidth = w;
    ctx.beginPath();
    ctx.moveTo(a[0], a[1]);
    ctx.lineTo(b[0], b[1]);
    ctx.stroke();
  }
}

function onPicture(event) {
  const box = $("profile-line").getBoundingClientRect();
  return [event.clientX - box.left, event.clientY - box.top];
}

async function profileAlong(a, b) {
  const job = state.job.id;
  state.overlayFrame ??= await get(`/api/merges/${job}/sem-overlay`);
  const f = state.overlayFrame;
  const c = $("profile-line");
  const toMosaic = ([px, py]) => {
    const col = (px / c.clientWidth) * f.box[2] - 0.5; // the picture's pixel centres
    const row = (py / c.clientHeight) * f.box[3] - 0.5;
    const m = f.pixel_to_mosaic;
    return [m[0][0] * col + m[0][1] * row + m[0][2], m[1][0] * col + m[1][1] * row + m[1][2]];
  };
  const [x0, y0] = toMosaic(a);
  const [x1, y1] = toMosaic(b);
  const cut = await get(`/api/merges/${job}/sem-profile?x0=${x0}&y0=${y0}&x1=${x1}&y1=${y1}&samples=240`);
  $("profile-plot").hidden = false;
  plotProfile($("profile-plot"), cut);
}

$("profile-line").addEventListener("pointerdown", (event) => {
  event.preventDefault();
  $("profile-line").setPointerCapture(event.pointerId);
  state.lineStart = onPicture(event);
});
$("profile-line").addEventListener("pointermove", (event) => {
  if (state.lineStart) drawLine(state.lineStart, onPicture(event));
});
$("profile-line").addEventListener("pointerup", (event) => {
  const a = state.lineStart;
  state.lineStart = null;
  if (!a) return;
  const b = onPicture(event);
  if (Math.hypot(b[0] - a[0], b[1] - a[1]) < 4) return clearLine(); // a click, not a line
  drawLine(a, b);
  userAct(() => profileAlong(a, b));
});

$("register-sem").addEventListener("click", () =>
  userAct(async () => {
    if (!sem.image) throw new Error("Acquire or upload an SEM image of this place first (above).");
    $("registration").textContent = "Registering …";
    showRegistration(await post(`/api/merges/${state.job.id}/sem-registration`, { sem: sem.image.meta.id }));
  }),
);

$("apply-registration").addEventListener("click", () =>
  userAct(async () => {
    const found = await post(`/api/merges/${state.job.id}/sem-registration/apply`);
    $("sem-calibration").textContent = calibrationText(found);
    $("apply-registration").hidden = true;
  }),
);

$("overlay-opacity").addEventListener("change", showOverlay);
$("overlay-blink").addEventListener("change", () => {
  clearInterval(state.blink);
  if ($("overlay-blink").checked) {
    state.blink = setInterval(() => {
      state.blinkOn = !state.blinkOn;
      showOverlay();
    }, 700);
  } else showOverlay();
});

// -- instrument -------------------------------------------------------------------------------

let instrumentReads = 0;

async function loadInstrument() {
  const read = ++instrumentReads;
  const s = await get("/api/instrument");
  if (read !== instrumentReads) return; // a later read is under way: an older answer must not overwrite it
  $("instrument-state").textContent = `instrument: ${s.state}`;
  $("instrument-state").className = `pill ${{ idle: "ok", running: "busy", fault: "bad", error: "bad" }[s.state]}`;
  const safe = $("safe-state");
  safe.textContent = s.safe_state ? "SAFE: tip retracted" : s.safe_state === false ? "TIP ENGAGED" : "safe state unknown";
  safe.className = `pill ${s.safe_state ? "ok" : "bad"}`;
  $("inst-state").textContent = s.message ? `${s.state}: ${s.message}` : s.state;
  $("inst-x").textContent = um(s.positions && s.positions.stage_x);
  $("inst-y").textContent = um(s.positions && s.positions.stage_y);
  $("inst-z").textContent = nm(s.positions && s.positions.robot_z_fine_extension);
  $("inst-df").textContent = s.frequency_shift === null ? "—" : `${s.frequency_shift.toFixed(2)} Hz`;
}

// -- the event stream -------------------------------------------------------------------------

function logEvent(event) {
  const li = document.createElement("li");
  li.textContent = `${event.time.slice(11, 19)} ${event.message}`;
  if (event.kind === "fault") li.className = "fault";
  const log = $("event-log");
  log.append(li);
  while (log.children.length > 300) log.firstElementChild.remove();
  log.scrollTop = log.scrollHeight;
}

function onEvent(event) {
  state.lastEvent = Math.max(state.lastEvent, event.id);
  const chatter = (event.kind === "merge" && event.data.state === "running") || (event.kind === "live" && event.data.patches_merged !== undefined);
  if (!chatter) logEvent(event);
  const mine = state.run && event.run_id === state.run.id;
  if (event.kind === "run" && event.run_id) {
    // the instrument first: a run shown as ended beside a tip still shown engaged misleads
    act(async () => {
      await act(loadInstrument);
      await (mine ? loadRun(event.run_id) : refreshRuns(event.run_id));
    });
  } else if (event.kind === "patch" && mine) {
    state.run.current_patch = event.data.step === "stored" ? null : event.data.patch;
    state.run.current_step = event.data.step === "stored" ? null : event.data.step;
    renderRun();
  } else if (event.kind === "progress" && mine) {
    state.run.progress = { stored: event.data.stored, total: event.data.total };
    const cell = $("patch-grid").querySelector(`[data-index="${event.data.patch}"]`);
    showPatch($("patch-grid"), event.run_id, event.data.patch, act, cell?.dataset.quality === "rescanned");
    renderRun();
    $("merge-start").disabled = event.data.stored < 2;
  } else if (event.kind === "merge" && event.data.job) {
    if (!state.job || state.job.id !== event.data.job) {
      if (!mine) return;
      startMerge({ id: event.data.job });
    }
    if (event.data.iteration !== undefined) state.residuals.push([event.data.iteration, event.data.residual]);
    renderMerge({ state: event.data.state, progress: event.data.progress, message: event.data.message });
  } else if (event.kind === "live" && mine && event.data.passed !== undefined) {
    markQuality($("patch-grid"), event.data.patch, event.data.passed ? "ok" : "failed", event.data.reason);
  } else if (event.kind === "rescan" && mine) {
    markQuality($("patch-grid"), event.data.patch, event.data.quality || "rescanned", event.data.reason);
  } else if (event.kind === "sem" && event.data.calibration) {
    act(loadCalibration);
  } else if (event.kind === "fault" || event.kind === "simulation") {
    act(loadInstrument);
  } else if (event.kind === "lock") {
    act(loadLock);
  }
}

function listen() {
  const source = new EventSource(`/api/events?after=${state.lastEvent}`);
  for (const kind of ["run", "patch", "progress", "merge", "fault", "request", "recovery", "sem", "simulation", "reconcile", "lock"]) {
    source.addEventListener(kind, (e) => onEvent(JSON.parse(e.data)));
  }
  source.onerror = () => {
    // closed (an expired login's stream is refused): a new access cookie first, then again
    if (source.readyState === EventSource.CLOSED) setTimeout(() => refreshSession().finally(listen), 2000);
  };
}

// -- start ------------------------------------------------------------------------------------

/** The 3D viewer, for a browser that holds the token (the viewer checks a cookie for it). */
async function openViewer() {
  const viewer = await act(() => get("/api/instrument/viewer"));
  const say = (text) => ($("viewer").srcdoc = `<p style='font:14px system-ui'>${text}</p>`);
  if (!viewer || !viewer.enabled) return say("The 3D viewer is off (MOSAIC_VIEWER=false).");
  const users = state.mode === "users";
  if (!users && !token()) return say("Enter the API token (above) to open the 3D viewer.");
  try {
    await post("/api/instrument/viewer/session");
  } catch (err) {
    return say(`The 3D viewer needs ${users ? "a login" : "the API token"}: ${err.message}`);
  }
  $("viewer").removeAttribute("srcdoc");
  $("viewer").src = `${location.protocol}//${location.hostname}:${viewer.port}/`;
}

let viewerWanted = false; // the page has started: a token typed from now on opens the viewer

async function start() {
  // before the first wait: a token typed while the page still loads is kept, not overwritten
  $("token").value = token();
  $("token").addEventListener("change", (e) => {
    setToken(e.target.value);
    if (viewerWanted) act(openViewer);
  });
  const who = await act(startSession);
  if (!who) return; // on the way to the login page (or the server did not answer)
  state.mode = who.mode;
  // where the event stream will start, taken before anything is read: an event between the
  // first reads and the stream's start (a lock released, a run ended) is replayed, never lost
  const latest = await act(() => get("/api/events/latest"));
  state.lastEvent = latest ? latest.id : 0;
  wireLock(userAct);
  await act(loadLock);
  await act(loadInstrument);
  await act(loadCalibration);
  await act(() => refreshRuns());
  listen();
  viewerWanted = true;
  await openViewer(); // with the token typed so far (a token typed later opens it again)
  const sems = await act(() => get("/api/sem"));
  // the latest image, unless the operator already asked for one while the page started
  if (sems && sems.length && sem.loads === 0) await act(() => sem.load(sems[sems.length - 1]));
}

start();
