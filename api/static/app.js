// The web page of `oga serve`: submit a program, watch its job, open the report, download tables.
// Every request goes through api(), which sends the API key the user typed (header X-API-Key,
// kept in sessionStorage) and turns an error answer into an ApiError with the server's words.
"use strict";

const $ = (id) => document.getElementById(id);
const KEY_STORAGE = "oga.apiKey";
const POLL_MS = 400;
const FINISHED = ["succeeded", "failed", "cancelled"];
const FORMAT_OF_SUFFIX = { csv: "csv", json: "json" };  // any other suffix: G-code

let shown = null;       // the job on display: {id, source, ...} as GET /v1/jobs/{id}
let pollTimer = null;

class ApiError extends Error {
  constructor(status, body) {
    super(body.message || `HTTP ${status}`);
    this.status = status;
    this.body = body;
  }
}

async function api(path, { method = "GET", json = undefined } = {}) {
  const headers = {};
  const key = $("api-key").value.trim();
  if (key) headers["X-API-Key"] = key;
  if (json !== undefined) headers["Content-Type"] = "application/json";
  let resp;
  try {
    resp = await fetch(path, { method, headers,
                               body: json === undefined ? undefined : JSON.stringify(json) });
  } catch (err) {
    throw new ApiError(0, { message: `the server cannot be reached (${err.message})` });
  }
  if (!resp.ok) {
    let body;
    try { body = await resp.json(); } catch { body = { message: `HTTP ${resp.status}` }; }
    throw new ApiError(resp.status, body);
  }
  return resp;
}

const getJson = async (path) => (await api(path)).json();

// -- messages ---------------------------------------------------------------------------------

function errorWords(err) {
  if (!(err instanceof ApiError)) return `Unexpected error in the page: ${err.message}`;
  if (err.status === 401) {
    return "This server needs an API key: type it in the API key field at the top " +
           `(the server said: ${err.message}).`;
  }
  return err.message;
}

// An error body (answer or failed job) as elements: the message, where in the program, violations.
function errorNodes(body, program) {
  const nodes = [Object.assign(document.createElement("p"), { textContent: body.message })];
  if (body.line) {
    const where = `Line ${body.line}` + (body.column ? `, column ${body.column}` : "");
    const text = program.split("\n")[body.line - 1];
    const pre = document.createElement("pre");
    pre.textContent = text === undefined ? where
      : `${where}:\n${text}\n${" ".repeat(Math.max(0, (body.column || 1) - 1))}^`;
    nodes.push(pre);
  }
  if (body.violations && body.violations.length) {
    const ul = document.createElement("ul");
    for (const v of body.violations) ul.append(Object.assign(document.createElement("li"),
                                                              { textContent: v }));
    nodes.push(ul);
  }
  return nodes;
}

function say(kind, ...nodes) {
  const box = $("message");
  box.className = kind;
  box.replaceChildren(...nodes.map((n) => typeof n === "string"
    ? Object.assign(document.createElement("p"), { textContent: n }) : n));
  box.hidden = nodes.length === 0;
}

function sayError(err) {
  if (err instanceof ApiError && err.status !== 401) say("error", ...errorNodes(err.body, ""));
  else say("error", errorWords(err));
}

// -- the server: machines, option defaults, recent jobs ---------------------------------------

// the horizon's default depends on the mode (from /openapi.json)
let npDefaults = {};

function showNpDefault() {
  const value = npDefaults[$("mode").value];
  $("np").placeholder = value === undefined ? "default" : `default ${value}`;
}

async function loadServer() {
  try {
    const health = await getJson("/healthz");
    $("server").textContent = `server ${health.version}, ${health.workers_alive} worker(s)`;
    const [machines, schema] = await Promise.all([getJson("/v1/machines"),
                                                  getJson("/openapi.json")]);
    const select = $("machine");
    const was = select.value || "ucp710";
    select.replaceChildren(...machines.items.map((m) => Object.assign(
      document.createElement("option"),
      { value: m.name, textContent: `${m.name} (axes ${m.axes.join(", ").toUpperCase()})` })));
    if (machines.items.some((m) => m.name === was)) select.value = was;
    const defaults = schema.components.schemas.OptimizeOptions.properties;
    npDefaults = defaults.np.default_per_mode;
    showNpDefault();
    $("tolerance").placeholder = `default ${defaults.tolerance.default}`;
    say("info");
    await loadJobs();
  } catch (err) {
    sayError(err);
  }
}

async function loadJobs() {
  const page = await getJson("/v1/jobs?limit=10");
  $("jobs").tBodies[0].replaceChildren(...page.items.map((job) => {
    const tr = document.createElement("tr");
    const cells = [new Date(job.created_at).toLocaleString(), job.source || "(unnamed)",
                   job.machine, job.status];
    for (const c of cells) tr.append(Object.assign(document.createElement("td"), { textContent: c }));
    const show = Object.assign(document.createElement("button"),
                               { type: "button", className: "small", textContent: "Show" });
    show.addEventListener("click", () => watch(job.id));
    tr.append(document.createElement("td"));
    tr.lastChild.append(show);
    return tr;
  }));
}

// -- submitting -------------------------------------------------------------------------------

function numberField(id, label, parse) {
  const input = $(id);
  if (!input.checkValidity()) throw new Error(`${label}: ${input.validationMessage}`);
  return input.value === "" ? undefined : parse(input.value);
}

function checked(name) {
  return [...document.querySelectorAll(`input[name=${name}]:checked`)].map((c) => c.value);
}

function options() {
  const opts = { mode: $("mode").value, gains: checked("gains") };
  if ($("nominal").checked) opts.nominal = true;
  const adjust = checked("adjust");
  if (adjust.length) opts.adjust = adjust;
  if ($("baseline").value === "fixed") {
    const kp = numberField("baseline-kp", "Baseline Kp", Number);
    const kf = numberField("baseline-kf", "Baseline Kf", Number);
    if (kp === undefined || kf === undefined) throw new Error("Baseline: give both Kp and Kf");
    opts.baseline = [kp, kf];
  }
  const fields = [["np", "np", "Horizon np", (v) => parseInt(v, 10)],
                  ["feed", "feed", "Feed", Number],
                  ["tolerance", "tolerance", "Tolerance", Number]];
  for (const [id, key, label, parse] of fields) {
    const value = numberField(id, label, parse);
    if (value !== undefined) opts[key] = value;
  }
  return opts;
}

async function submit(event) {
  event.preventDefault();
  const program = $("program").value;
  if (!program.trim()) {
    say("error", "Choose a program file or paste a program first.");
    return;
  }
  let body;
  try {
    body = { toolpath: { format: $("format").value, content: program, name: $("name").value },
             machine: $("machine").value || "ucp710", options: options() };
  } catch (err) {
    say("error", err.message);
    return;
  }
  $("submit").disabled = true;
  try {
    const accepted = await (await api("/v1/jobs", { method: "POST", json: body })).json();
    say("info");
    await watch(accepted.id);
  } catch (err) {
    if (err instanceof ApiError && err.status === 422) {
      say("error", ...errorNodes(err.body, program));
      selectLine(err.body.line);
    } else {
      sayError(err);
    }
  } finally {
    $("submit").disabled = false;
  }
}

function selectLine(line) {
  if (!line) return;
  const text = $("program").value;
  let start = 0;
  for (let i = 1; i < line && start !== -1; i++) start = text.indexOf("\n", start) + 1 || -1;
  if (start === -1) return;
  const end = text.indexOf("\n", start);
  $("program").focus();
  $("program").setSelectionRange(start, end === -1 ? text.length : end);
}

async function readFile() {
  const file = $("file").files[0];
  if (!file) return;
  $("program").value = await file.text();
  $("name").value = file.name;
  const suffix = file.name.includes(".") ? file.name.split(".").pop().toLowerCase() : "";
  $("format").value = FORMAT_OF_SUFFIX[suffix] || "gcode";
}

// -- the job on display -----------------------------------------------------------------------

async function watch(id) {
  clearTimeout(pollTimer);
  shown = { id };
  $("job").hidden = false;
  $("job-id").textContent = id;
  $("results").hidden = true;
  $("job-error").hidden = true;
  $("outcome").textContent = "";
  await poll(id);
}

async function poll(id) {
  let job;
  try {
    job = await getJson(`/v1/jobs/${encodeURIComponent(id)}`);
  } catch (err) {
    sayError(err);
    return;
  }
  if (!shown || shown.id !== id) return;  // another job was chosen meanwhile
  const changed = shown.status !== job.status;
  shown = job;
  showJob(job);
  if (changed && job.status === "succeeded") {
    await (job.links && job.links.machine ? showIdentified(job) : showSummary(id)).catch(sayError);
  }
  if (changed) await loadJobs().catch(sayError);
  if (!FINISHED.includes(job.status)) {
    pollTimer = setTimeout(() => poll(id), POLL_MS);
  }
}

function showJob(job) {
  $("job-source").textContent = job.source || "(unnamed program)";
  $("job-machine").textContent = job.machine;
  $("job-status").textContent = job.status;
  $("job-status").className = job.status;
  $("job-progress").value = job.status === "succeeded" ? 1 : job.progress;
  const end = job.finished_at ? new Date(job.finished_at) : new Date();
  const seconds = (end - new Date(job.created_at)) / 1000;
  $("job-elapsed").textContent = `${Math.round(100 * $("job-progress").value)} %, ` +
                                 `${seconds.toFixed(1)} s since submitted`;
  $("cancel").hidden = FINISHED.includes(job.status);
  $("results").hidden = job.status !== "succeeded";
  $("job-error").hidden = !job.error;
  $("job-error").replaceChildren(...(job.error ? errorNodes(job.error, "") : []));
}

// The table buttons, which only an optimisation has (every succeeded job has a report).
function showDownloads(on) {
  $("open-report").hidden = false;
  document.querySelector("#results .downloads").hidden = !on;
}

// An identification job (POST /v1/identify) has a machine file and its fit report, not a
// table: say where the file is.
async function showIdentified(job) {
  showDownloads(false);
  $("outcome").textContent = `An identification: the identified machine file is at ` +
                             `GET ${job.links.machine}; the report shows the fit.`;
}

// The outcome in one line, from the job's summary (as `oga optimize --summary`).
async function showSummary(id) {
  const s = await getJson(`/v1/jobs/${encodeURIComponent(id)}/summary`);
  if (shown.id !== id) return;
  showDownloads(true);
  const um = (key) => `${s.baseline[key].toFixed(2)} \u2192 ${s.optimized[key].toFixed(2)} \u00b5m`;
  $("outcome").textContent =
    `Contour error rms ${um("rms_ce_um")}, max ${um("max_ce_um")} ` +
    `(MSE ratio ${s.ratio_mse.toFixed(3)}); largest following error ${followingError(s)}; ` +
    `${s.samples} samples, ${s.duration_s} s of motion; ` +
    `limits ${s.limits_ok ? "ok" : "VIOLATED"}, stability ${s.stability_ok ? "ok" : "NOT OK"}` +
    (s.kept_baseline ? "; the baseline gains were kept (no better schedule found)." : ".");
}

// Per contouring axis, the largest following error before and after, in mm, and the share
// of the machine's limit where it sets one (summaries stored before the limit existed have none).
function followingError(s) {
  const mm = (um) => (um / 1000).toFixed(3);
  const ratio = s.ferror_ratio_to_limit || {};
  return s.contouring_axes.map((a) =>
    `${a} ${mm(s.baseline.track_max_um[a])} \u2192 ${mm(s.optimized.track_max_um[a])} mm` +
    (ratio[a] == null ? "" : ` (${(100 * ratio[a]).toFixed(0)} % of its limit)`)).join(", ");
}

function stem() {
  const name = (shown.source || "").split("/").pop();
  return (name.includes(".") ? name.slice(0, name.lastIndexOf(".")) : name) || shown.id;
}

async function cancel() {
  try {
    showJob(await (await api(`/v1/jobs/${shown.id}`, { method: "DELETE" })).json());
    await loadJobs();
  } catch (err) {
    sayError(err);
  }
}

// The report needs the API key, so it is fetched here and shown from a blob: URL. The tab is
// opened at the click (no popup blocker) and pointed at the report once it has arrived.
async function openReport() {
  const tab = window.open("", "_blank");
  if (!tab) {
    say("error", "The browser blocked the new tab: allow pop-ups for this page, " +
                 "or download the report.");
    return;
  }
  tab.document.title = "oga report";
  tab.document.body.textContent = "Building the report...";
  try {
    const blob = await (await api(`/v1/jobs/${shown.id}/report`)).blob();
    tab.location.href = URL.createObjectURL(blob);
  } catch (err) {
    tab.close();
    sayError(err);
  }
}

async function download(event) {
  const button = event.target.closest("button");
  if (!button) return;
  try {
    const resp = await api(`/v1/jobs/${shown.id}/${button.dataset.path}`);
    const named = /filename="([^"]+)"/.exec(resp.headers.get("Content-Disposition") || "");
    const link = document.createElement("a");
    link.href = URL.createObjectURL(await resp.blob());
    link.download = named ? named[1] : stem() + button.dataset.suffix;
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10000);
  } catch (err) {
    sayError(err);
  }
}

// -- wiring -----------------------------------------------------------------------------------

function keyChanged() {
  sessionStorage.setItem(KEY_STORAGE, $("api-key").value.trim());
  loadServer();
}

function showBaselineFields() {
  for (const el of document.querySelectorAll(".fixed")) {
    el.hidden = $("baseline").value !== "fixed";
  }
}

document.addEventListener("DOMContentLoaded", () => {
  $("api-key").value = sessionStorage.getItem(KEY_STORAGE) || "";
  $("api-key").addEventListener("change", keyChanged);
  $("file").addEventListener("change", () => readFile().catch(sayError));
  $("baseline").addEventListener("change", showBaselineFields);
  $("mode").addEventListener("change", showNpDefault);
  $("job-form").addEventListener("submit", submit);
  $("cancel").addEventListener("click", cancel);
  $("open-report").addEventListener("click", openReport);
  $("results").querySelector(".downloads").addEventListener("click", download);
  $("refresh").addEventListener("click", () => loadJobs().catch(sayError));
  showBaselineFields();
  loadServer();
});
