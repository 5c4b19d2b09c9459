// The autotune console's page: live data from the console's websocket, drawn on canvases.
// No library: everything here ships with the Python package and works offline.
"use strict";

const S = {
  ws: null, nextId: 1, history: 600, rules: [],
  loops: {},          // loop → {status, info}
  alive: new Set(),   // loops whose plant announces them
  aliveKnown: false,  // the services' tokens heard (an empty set then means no plant is up)
  running: new Set(), // loops with a run in progress
  leftAt: {},         // loop → Date.now() when its run's token went (its result may follow)
  resultRuns: new Set(), // the runs whose result (or an apply's) the page has had
  trends: {},         // loop → {t, pv, sp, op}
  progress: {},       // loop → last TuneProgress
  phases: {},         // loop → {run, list}: the phases its last run went through
  results: {},        // loop → {result, predicted}
  selected: null, chosenRule: null, runRows: [], ticked: [],
  dirty: true,
};

const $ = (id) => document.getElementById(id);
// d significant digits, the zeros after a decimal point dropped (4000 stays 4000: an integer's
// own zeros are digits, and the old pattern printed lvl2's Ti of 4000 s as "4 s")
const fmt = (v, d = 4) => (v === null || v === undefined || !isFinite(v)) ? "—" : Number(v).toPrecision(d).replace(/(\.\d*?)0+(?=e|$)/, "$1").replace(/\.(?=e|$)/, "");
const fixed = (v, d) => (v === null || v === undefined || !isFinite(v)) ? "—" : Number(v).toFixed(d);
const esc = (s) => String(s ?? "").replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));

function say(text, ok = true) {
  const li = document.createElement("li");
  li.textContent = `${new Date().toLocaleTimeString()}  ${text}`;
  if (!ok) li.className = "bad";
  $("messages").prepend(li);
  while ($("messages").children.length > 50) $("messages").lastChild.remove();
}

// --- the websocket -----------------------------------------------------------------------------

function connect() {
  const ws = new WebSocket(`ws://${location.host}/ws`);
  S.ws = ws;
  ws.onopen = () => { $("svc-link").dataset.up = "true"; };
  ws.onclose = () => {
    $("svc-link").dataset.up = "false";
    for (const s of ["plant_sim", "tuner", "logger"]) $(`svc-${s}`).dataset.up = "false";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => handle(JSON.parse(ev.data));
}

function send(msg) {
  if (!S.ws || S.ws.readyState !== WebSocket.OPEN) { say("not connected to the console", false); return null; }
  msg.id = S.nextId++;
  S.ws.send(JSON.stringify(msg));
  return msg.id;
}

const handlers = {
  hello(m) {
    S.history = m.history; S.rules = m.rules;
    $("prefix").textContent = `prefix ${m.prefix} · runs ${m.runs}`;
    const sel = $("rule-select");
    sel.innerHTML = '<option value="auto">auto (recommended)</option>' +
      m.rules.map((r) => `<option value="${esc(r.name)}">${esc(r.name)}</option>`).join("");
  },
  services(m) {
    for (const s of ["plant_sim", "tuner", "logger"]) {
      const el = $(`svc-${s}`);
      el.dataset.up = String(m[s].length > 0);
      el.title = m[s].length ? `up: ${m[s].join(", ")}` : "not on the bus";
    }
    const running = new Set(m.running);
    for (const loop of S.running) {
      if (running.has(loop)) continue;
      // its run's token went: a result normally follows at once; none within ENDED_WAIT and the
      // last phase shown is said to be a run that ended without one (a paused or killed tuner
      // left the page showing "verify" as if the run went on)
      S.leftAt[loop] = Date.now();
      setTimeout(() => { if (loop === S.selected) renderProgress(); }, ENDED_WAIT + 100);
    }
    for (const loop of running) delete S.leftAt[loop];
    S.alive = new Set(m.loops); S.running = running; S.aliveKnown = true;
    renderLoops(); renderTuneButtons(); renderProgress();
  },
  loop(m) {
    const cur = S.loops[m.loop] || {};
    S.loops[m.loop] = { status: m.status || cur.status, info: m.info || cur.info };
    if (!S.selected) select(m.loop);
    renderLoops();
  },
  trend(m) {
    let tr = S.trends[m.loop];
    if (m.reset || !tr || (m.t.length && tr.t.length && m.t[0] < tr.t[tr.t.length - 1] - 1e-9 && m.t[0] < 1e-9)) {
      tr = S.trends[m.loop] = { t: [], pv: [], sp: [], op: [] };
    }
    for (const k of ["t", "pv", "sp", "op"]) tr[k].push(...m[k]);
    const last = tr.t[tr.t.length - 1];
    let cut = 0;
    while (cut < tr.t.length && tr.t[cut] < last - S.history) cut++;
    if (cut) for (const k of ["t", "pv", "sp", "op"]) tr[k].splice(0, cut);
    if (m.loop === S.selected) S.dirty = true;
    renderLoops();  // the card's figures are its last sample's (a status may be long ago)
  },
  progress(m) {
    const seen = S.phases[m.loop];
    if (!seen || seen.run !== m.run_id) S.phases[m.loop] = { run: m.run_id, list: [m.phase] };
    else if (seen.list[seen.list.length - 1] !== m.phase) seen.list.push(m.phase);
    const prev = S.progress[m.loop];
    if (prev && prev.run_id !== m.run_id) delete S.leftAt[m.loop];  // a new run: its own clock
    S.progress[m.loop] = m;
    if (S.aliveKnown && !S.running.has(m.loop) && S.leftAt[m.loop] === undefined) {
      // a run not (or no longer) on the bus, e.g. the last progress a reloaded page is sent
      S.leftAt[m.loop] = Date.now();
      setTimeout(() => { if (m.loop === S.selected) renderProgress(); }, ENDED_WAIT + 100);
    }
    if (m.loop === S.selected) renderProgress();
  },
  result(m) {
    S.results[m.loop] = m;
    S.resultRuns.add(m.result.run_id);
    if (m.applied_by) S.resultRuns.add(m.applied_by.run_id);
    setTimeout(loadRuns, 1500);  // the logger finishes the run's file once the result is out
    if (m.loop === S.selected) { S.chosenRule = null; renderResult(); renderProgress(); }
    if (!m.earlier) say(`result of run ${m.result.run_id} on ${m.loop}: ${m.result.status}` + (m.result.reason ? ` (${m.result.reason})` : ""), ["ok", "proposed"].includes(m.result.status));
  },
  action(m) {
    say(m.message, m.ok);
    if (m.action === "tune" && m.stage === "accepted") renderTuneButtons();
  },
};

function handle(m) { (handlers[m.type] || (() => {}))(m); }

// --- the loops ---------------------------------------------------------------------------------

function select(loop) {
  S.selected = loop; S.chosenRule = null; S.dirty = true;
  $("trend-title").textContent = `Trend of ${loop}`;
  $("tune-loop").textContent = loop;
  renderLoops(true); renderProgress(); renderResult(); renderTuneButtons();
}

function gainsText(g) {
  if (!g) return "";
  return `Kc ${fmt(g.kc)} · Ti ${g.ti === null ? "off" : fmt(g.ti) + " s"} · Td ${fmt(g.td)} s${g.beta !== undefined && g.beta !== 1 ? ` · β ${fmt(g.beta)}` : ""}`;
}

// every loop's status message asked for a redraw of every card: with 600 loops the page
// took seconds to answer a click; redrawn at most every LOOPS_EVERY ms (at once on a click)
const LOOPS_EVERY = 250;
let loopsTimer = null;
function renderLoops(now = false) {
  if (now) { clearTimeout(loopsTimer); loopsTimer = null; drawLoops(); return; }
  if (loopsTimer !== null) return;
  loopsTimer = setTimeout(() => { loopsTimer = null; drawLoops(); }, LOOPS_EVERY);
}

function drawLoops() {
  const ids = Object.keys(S.loops).sort();
  if (!ids.length) return;
  $("loops").innerHTML = ids.map((id) => {
    const { status: st, info } = S.loops[id];
    const units = info ? info.pv_units : "";
    // the only plant gone leaves no loop alive: every card says so (it said nothing)
    const off = S.aliveKnown && !S.alive.has(id) ? " offline" : "";
    // SP, PV and OP of its last sample where that is newer than its last status (in realtime
    // a status comes seldom: a card showed a PV 475 s old as if live); its time always said
    const tr = S.trends[id], k = tr && tr.t.length ? tr.t.length - 1 : -1;
    const bySample = k >= 0 && (!st || tr.t[k] >= st.t);
    const fig = bySample ? { sp: tr.sp[k], pv: tr.pv[k], op: tr.op[k], t: tr.t[k] } : st;
    const lease = st && st.leased_by ? `<div class="muted">held by ${esc(st.leased_by)}</div>` : "";
    const run = S.running.has(id) ? ' <span class="muted">tuning…</span>' : "";
    return `<div class="loop${id === S.selected ? " selected" : ""}${off}" data-loop="${esc(id)}">
      <span class="id">${esc(id)}</span>${run}<span class="mode">${st ? esc(st.mode) : "?"}</span>
      <div class="muted">${esc(info ? info.description : "")}</div>
      <div class="figs">SP ${fig ? fmt(fig.sp) : "—"} · PV ${fig ? fmt(fig.pv) : "—"} ${esc(units)} · OP ${fig ? fmt(fig.op) : "—"} %</div>
      <div class="figs gains">${gainsText(st && st.gains)}</div>${lease}
      ${fig ? `<div class="muted">as of t = ${fmt(fig.t)} s (its last ${bySample ? "sample" : "status"})</div>` : ""}
      ${off ? '<div class="muted">plant not on the bus</div>' : ""}</div>`;
  }).join("");
  $("loops").onclick ||= (ev) => { const el = ev.target.closest(".loop"); if (el) select(el.dataset.loop); };
}

// --- drawing -----------------------------------------------------------------------------------

function niceRange(lo, hi) {
  if (!isFinite(lo) || !isFinite(hi)) return [0, 1];
  if (hi - lo < 1e-9) { const d = Math.max(Math.abs(hi) * 0.01, 1e-3); return [lo - d, hi + d]; }
  const pad = 0.06 * (hi - lo);
  return [lo - pad, hi + pad];
}

// round tick values (1, 2 or 5 × 10^k apart), about n of them within [lo, hi]
function niceTicks(lo, hi, n) {
  const raw = (hi - lo) / Math.max(n, 1);
  if (!(raw > 0) || !isFinite(raw)) return [lo];
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const r = raw / mag, step = (r < 1.5 ? 1 : r < 3 ? 2 : r < 7 ? 5 : 10) * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}

function fitCanvas(c) {
  const w = c.clientWidth || c.width;
  if (c.width !== w) c.width = w;
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  return g;
}

// one pane: series [{x, y, color, width, step}] over [x0, x1] × [y0, y1] in the box
function pane(g, box, x0, x1, y0, y1, series, label) {
  const [L, T, W, H] = box;
  const X = (x) => L + ((x - x0) / (x1 - x0)) * W;
  const Y = (y) => T + H - ((y - y0) / (y1 - y0)) * H;
  g.strokeStyle = "#ccc"; g.lineWidth = 1; g.strokeRect(L, T, W, H);
  g.fillStyle = "#555"; g.font = "11px system-ui";
  for (const v of niceTicks(y0, y1, 4)) {
    const y = Y(v);
    g.strokeStyle = "#eee"; g.beginPath(); g.moveTo(L, y); g.lineTo(L + W, y); g.stroke();
    g.fillText(fmt(v, 4), 2, y + 4);
  }
  g.fillText(label, L + 4, T + 12);
  g.save(); g.beginPath(); g.rect(L, T, W, H); g.clip();
  for (const s of series) {
    if (!s.x.length) continue;
    g.strokeStyle = s.color; g.lineWidth = s.width || 1.2; g.setLineDash(s.dash || []);
    g.beginPath();
    for (let i = 0; i < s.x.length; i++) {
      const x = X(s.x[i]), y = Y(s.y[i]);
      if (i === 0) g.moveTo(x, y);
      else if (s.step) { g.lineTo(x, Y(s.y[i - 1])); g.lineTo(x, y); } else g.lineTo(x, y);
    }
    g.stroke();
  }
  g.restore(); g.setLineDash([]);
  return { X, Y };
}

function drawTrend() {
  const c = $("trend"), g = fitCanvas(c);
  const tr = S.trends[S.selected];
  const info = (S.loops[S.selected] || {}).info;
  if (!tr || !tr.t.length) {
    g.fillStyle = "#777"; g.font = "13px system-ui";
    g.fillText(S.selected ? `no samples of ${S.selected} yet (a lockstep loop moves only while driven)` : "", 60, 40);
    return;
  }
  const t1 = tr.t[tr.t.length - 1], t0 = Math.min(tr.t[0], t1 - 1e-6);
  const L = 60, W = c.width - L - 10, H1 = Math.round(c.height * 0.62) - 20, H2 = c.height - H1 - 56;
  const [a, b] = niceRange(Math.min(...tr.pv, ...tr.sp), Math.max(...tr.pv, ...tr.sp));
  pane(g, [L, 6, W, H1], t0, t1, a, b, [
    { x: tr.t, y: tr.sp, color: "#c62828", step: true, dash: [5, 3] },
    { x: tr.t, y: tr.pv, color: "#1565c0" },
  ], `PV, setpoint${info ? " (" + info.pv_units + ")" : ""}`);
  const [c0, c1] = niceRange(Math.min(...tr.op), Math.max(...tr.op));
  pane(g, [L, H1 + 22, W, H2], t0, t1, c0, c1, [{ x: tr.t, y: tr.op, color: "#2e7d32", step: true }], "output (%)");
  g.fillStyle = "#555";
  for (const t of niceTicks(t0, t1, 6)) {
    const x = L + ((t - t0) / (t1 - t0)) * W;
    g.strokeStyle = "#ccc"; g.beginPath(); g.moveTo(x, c.height - 34); g.lineTo(x, c.height - 30); g.stroke();
    g.fillText(fmt(t, 5), Math.min(x - 10, L + W - 30), c.height - 18);
  }
  g.fillText("sim time (s)", L + W / 2 - 30, c.height - 4);
  $("trend-window").textContent = `last ${Math.round(t1 - t0)} s of sim time (keeps ${S.history} s)`;
}

function drawStep() {
  const c = $("step"), g = fitCanvas(c);
  const r = S.results[S.selected];
  const curves = r && r.predicted ? r.predicted : {};
  const names = Object.keys(curves).filter((n) => curves[n]);
  if (!names.length) return;
  const rec = r.result.recommended ? r.result.recommended.rule : r.result.rule;
  const chosen = S.chosenRule || rec;
  // the span the recommended and chosen curves take (each curve runs until it settles: a slow
  // rule's, hundreds of time scales long, squeezed the recommended one into the axis' first %)
  const shown = [rec, chosen].filter((n) => curves[n]);
  let xmax = 0, ymax = 1.2;
  for (const n of (shown.length ? shown : names)) { xmax = Math.max(xmax, curves[n].t[curves[n].t.length - 1]); }
  for (const n of [rec, chosen]) if (curves[n]) ymax = Math.max(ymax, Math.max(...curves[n].y) * 1.05);
  const upTo = (c) => { let k = c.t.length; while (k > 1 && c.t[k - 1] > xmax) k--; return { x: c.t.slice(0, k), y: c.y.slice(0, k) }; };
  const series = names.filter((n) => n !== rec && n !== chosen).map((n) => { const c = upTo(curves[n]); return { x: c.x, y: c.y.map((v) => Math.min(v, ymax)), color: "#ccc", width: 1 }; });
  series.push({ x: [0, xmax], y: [1, 1], color: "#c62828", dash: [4, 3] });
  if (curves[rec]) series.push({ x: curves[rec].t, y: curves[rec].y, color: "#ef6c00", width: 2.2 });
  if (chosen !== rec && curves[chosen]) series.push({ x: curves[chosen].t, y: curves[chosen].y, color: "#1565c0", width: 2 });
  pane(g, [50, 6, c.width - 60, c.height - 30], 0, xmax, -0.1, ymax, series, "PV / setpoint step");
  g.fillStyle = "#555";
  g.fillText(`0 … ${fmt(xmax, 3)} s`, c.width / 2 - 20, c.height - 8);
  $("step-legend").innerHTML = `predicted setpoint step on the identified model: <b style="color:#ef6c00">${esc(rec)}</b> (recommended)` +
    (chosen !== rec ? `, <b style="color:#1565c0">${esc(chosen)}</b> (chosen)` : "") + ", the other rules grey";
}

function frame() {
  if (S.dirty) { S.dirty = false; drawTrend(); }
  requestAnimationFrame(frame);
}

// --- tuning ------------------------------------------------------------------------------------

function renderTuneButtons() {
  const run = S.selected && S.running.has(S.selected);
  $("tune-start").disabled = !S.selected || run;
  $("tune-cancel").disabled = !run;
}

const ENDED_WAIT = 3000;  // ms after a run's token went before its missing result is told

// the run of progress ``p`` on ``loop`` went from the bus without a result (its token gone for
// ENDED_WAIT, no result of that run, nor an apply of it, on the page: a run aborted with its
// result, then another on the loop whose result came without progress, flagged the first)
function endedWithoutResult(loop, p) {
  if (!p || p.phase === "done" || S.running.has(loop)) return false;
  if (S.resultRuns.has(p.run_id)) return false;  // any run's, not the loop's last alone
  return S.leftAt[loop] !== undefined && Date.now() - S.leftAt[loop] >= ENDED_WAIT;
}

function renderProgress() {
  const p = S.progress[S.selected];
  $("progress-phase").textContent = p ? p.phase : "—";
  $("progress-t").textContent = p ? `${fmt(p.t, 5)} s` : "—";
  $("progress-cycles").textContent = p ? p.cycles : "—";
  $("progress-run").textContent = p ? p.run_id : "—";
  $("progress-ku").textContent = p && p.ku ? fmt(p.ku) : "—";
  $("progress-pu").textContent = p && p.pu ? `${fmt(p.pu)} s` : "—";
  $("progress-message").textContent = p ? p.message : "";
  if (endedWithoutResult(S.selected, p)) {
    $("progress-phase").textContent = `${p.phase} (ended, no result)`;
    $("progress-message").textContent = `run ${p.run_id} left the bus without a result: its tuner stopped, paused or lost the bus; the plant returns a loop whose lease lapses to its state before the test`;
  }
  const seen = S.phases[S.selected];
  $("progress-phases").textContent = seen ? seen.list.join(" → ") : "";
}

function tuneFields() {
  const f = $("tune-form").elements, out = {};
  out.method = f.method.value;
  out.rule = f.rule.value;
  out.aim = f.aim.value;
  for (const n of ["amplitude", "max-time", "max-overshoot", "max-op-noise"]) if (f[n].value.trim()) out[n] = f[n].value.trim();
  const lo = f["pv-lo"].value.trim(), hi = f["pv-hi"].value.trim();
  if (lo || hi) out["pv-limits"] = [lo, hi];
  out["no-apply"] = !f["apply-now"].checked;
  return out;
}

$("tune-start").onclick = () => {
  if (!S.selected) return;
  send({ type: "tune", loop: S.selected, fields: tuneFields() });
  say(`tune of ${S.selected} requested`);
};
$("tune-cancel").onclick = () => {
  const p = S.progress[S.selected];
  send({ type: "cancel", loop: S.selected, run_id: p ? p.run_id : null });
};

// --- the result --------------------------------------------------------------------------------

// a rule's predicted Ms, margins, overshoot and decay ratio; on a loop the model says is
// unstable they mean nothing, said so as `autotune tune` does (the page showed cc-pid on lvl1
// with GM 0.92, PM -7.57°, an overshoot of 3404.4 % and a decay ratio of 1.22 as figures)
// an Ms the measured point alone set (the model misses the plant there) is marked, as the CLI marks it
const FLOOR_NOTE = "Ms from the measured ultimate point alone: the model misses the plant there, so GM, PM, OS and DR are the model's, not the plant's";
const robustCells = (a) => (a.stable === false ? '<td colspan="6" class="bad">UNSTABLE on the model</td>' : `<td${a.ms_from_point ? ` title="${FLOOR_NOTE}"` : ""}>${fmt(a.ms, 3)}${a.ms_from_point ? "*" : ""}</td><td>${fmt(a.gain_margin, 3)}</td><td>${fmt(a.phase_margin_deg, 3)}</td><td>${fixed(a.overshoot_pct, 1)}</td><td>${fixed(a.decay_ratio, 2)}</td><td>${fixed(a.op_noise_pct, 2)}</td>`);

function renderResult() {
  const m = S.results[S.selected];
  const head = $("result-head"), thead = $("rules").tHead, tbody = $("rules").tBodies[0];
  if (!m) {
    head.textContent = "no result for this loop yet"; $("result-status").textContent = "";
    thead.innerHTML = tbody.innerHTML = ""; $("apply").disabled = $("reject").disabled = true;
    drawStep(); return;
  }
  const r = m.result, e = r.experiment || {}, units = r.pv_units || "PV unit";
  const per = /[/·*]/.test(units) ? `(${units})` : units;  // %/(m3/h), not %/m3/h
  const v = r.after;  // the verification of the gains the run applied, as measured
  const acc = r.acceptance || {};  // a setpoint weight against the overshoot (README)
  const weight = acc.setpoint_weight != null ? `, at setpoint weight β ${fmt(acc.setpoint_weight)} (${fixed(acc.overshoot_full_weight, 1)} % at full weight)` : "";
  const verified = v ? `<div id="result-verified">verified: overshoot ${fixed(v.overshoot, 1)} %, decay ratio ${fixed(v.decay_ratio, 2)}, settling ${fmt(v.settling_time, 3)} s, IAE ${fmt(v.iae_sp, 3)}, output noise ${fixed(v.op_noise, 2)} % (σ)${v.stable === false ? " — not stable" : ""}${weight}</div>` : "";
  $("result-status").textContent = `${r.status} · run ${r.run_id}`;
  const lags = Object.keys(e).filter((k) => k.startsWith("model_lag")).sort().map((k) => fmt(e[k])).join(", ");
  const model = e.model ? `model ${String(e.model).toUpperCase()}: K = ${fmt(e.model_gain)}${lags ? `, T = ${lags} s` : ""}, L = ${fmt(e.model_delay)} s` : "no model";
  head.innerHTML = `<div>${esc(r.applied_from ? `applying run ${r.applied_from}'s gains` : `${r.method} test, rule ${r.rule}`)}${r.reason ? " — " + esc(r.reason) : ""}</div>
    <div><b>K<sub>u</sub></b> = <span id="result-ku">${fmt(r.ku)}</span> %/${esc(per)} &nbsp; <b>P<sub>u</sub></b> = <span id="result-pu">${fmt(r.pu)}</span> s &nbsp; <span id="result-model">${esc(model)}</span></div>
    <div>${r.applied ? "new gains applied, loop in auto" : m.applied_by ? "" : !r.restored ? "" : ["proposed", "rejected"].includes(r.status) && r.gains && Object.keys(r.gains).length ? "loop as before the test: the gains wait for Apply" : "loop as before the test"}</div>${verified}
    ${m.applied_by ? `<div id="result-applied"><b>${esc(m.applied_by.rule)} applied</b> by run ${esc(m.applied_by.run_id)}: ${esc(m.applied_by.status)}${m.applied_by.applied ? ", verified, loop in auto" : ", not applied: the loop restored"}${m.applied_by.reason ? " (" + esc(m.applied_by.reason) + ")" : ""}</div>` : ""}
    ${r.recommended ? `<div class="muted">recommended: ${esc(r.recommended.rule)} (${esc(r.recommended.reason)})</div>` : ""}`;
  thead.innerHTML = `<tr><th>rule</th><th>Kc %/${esc(per)}</th><th>Ti s</th><th>Td s</th><th>Ms</th><th>GM</th><th>PM °</th><th>OS % (pred.)</th><th>DR (pred.)</th><th title="the output noise the gains make of the PV's, σ">OP σ % (pred.)</th></tr>`;
  const rec = r.recommended ? r.recommended.rule : r.rule;
  const chosen = S.chosenRule || rec;
  tbody.innerHTML = Object.entries(r.gains || {}).map(([name, g]) => {
    const a = (r.robustness || {})[name] || {}, isa = g.isa || {};
    const cls = [name === rec ? "recommended" : "", name === chosen ? "chosen" : ""].join(" ");
    return `<tr class="${cls}" data-rule="${esc(name)}"><td>${esc(name)}</td><td>${fmt(isa.kc)}</td><td>${isa.ti === null ? "off" : fmt(isa.ti)}</td><td>${fmt(isa.td)}</td>
      ${robustCells(a)}</tr>`;
  }).join("");
  for (const tr of tbody.rows) tr.onclick = () => { S.chosenRule = tr.dataset.rule; renderResult(); };
  const applied = r.applied || (m.applied_by && m.applied_by.applied);
  const pending = ["ok", "proposed", "rejected"].includes(r.status) && !applied && !r.applied_from && Object.keys(r.gains || {}).length > 0;
  $("apply").disabled = !pending;
  $("reject").disabled = !(pending || applied);
  $("apply").textContent = pending ? `Apply ${chosen}` : "Apply";
  drawStep();
}

$("apply").onclick = () => {
  const m = S.results[S.selected];
  if (!m) return;
  const r = m.result, rec = r.recommended ? r.recommended.rule : r.rule;
  const rule = S.chosenRule && S.chosenRule !== rec ? S.chosenRule : null;
  send({ type: "apply", run_id: r.run_id, rule });
  $("apply").disabled = true;
  say(`apply of run ${r.run_id}'s ${rule || rec} gains requested (verified as a tune)`);
};
$("reject").onclick = () => {
  const m = S.results[S.selected];
  if (m) send({ type: "reject", loop: S.selected, run_id: m.result.run_id });
  $("apply").disabled = $("reject").disabled = true;
};
// the gains the page shows as the loop's go with the request: a second press that came before
// the first one's change was shown is refused, not a revert of the revert
$("revert").onclick = () => {
  if (!S.selected) return;
  const st = (S.loops[S.selected] || {}).status;
  send({ type: "revert", loop: S.selected, gains: st ? st.gains : null });
};

// --- the recorded runs -------------------------------------------------------------------------

// an `autotune apply` run tests nothing: "apply of <run>", as `autotune runs` says "apply" (the
// console listed it as a relay run with no K_u, P_u)
const runMethod = (r) => (r.applied_from ? `apply of ${r.applied_from}` : r.method);

async function loadRuns() {
  try {
    const res = await fetch("/api/runs");
    S.runRows = await res.json();
  } catch (err) { say(`runs: ${err}`, false); return; }
  S.ticked = S.ticked.filter((f) => S.runRows.some((r) => r.file === f));
  $("runs").tBodies[0].innerHTML = S.runRows.slice().reverse().map((r) => `<tr data-file="${esc(r.file)}">
    <td><input type="checkbox" ${S.ticked.includes(r.file) ? "checked" : ""}></td><td>${esc((r.started || "").slice(0, 19))}</td>
    <td>${esc(r.loop)}</td><td>${esc(runMethod(r))}</td><td>${fmt(r.ku)}</td><td>${fmt(r.pu)}</td><td>${esc(r.rule)}</td>
    <td>${esc(r.status)}${r.reason ? ": " + esc(r.reason) : ""}${r.dropped ? ` <b class="warn">(${esc(r.dropped)} samples dropped: the record has gaps)</b>` : ""}</td><td><button type="button" class="open">report</button></td></tr>`).join("");
  for (const tr of $("runs").tBodies[0].rows) {
    tr.querySelector(".open").onclick = () => showReports([tr.dataset.file]);
    tr.querySelector("input").onchange = (ev) => {
      const f = tr.dataset.file;
      S.ticked = S.ticked.filter((x) => x !== f);
      if (ev.target.checked) S.ticked.push(f);
      $("compare").disabled = S.ticked.length !== 2;
    };
  }
  $("compare").disabled = S.ticked.length !== 2;
}

function showReports(files) {
  $("reports").innerHTML = files.map((f) => `<figure><figcaption>${esc(f)}</figcaption>
    <img alt="report of ${esc(f)}" src="/api/report.svg?file=${encodeURIComponent(f)}"></figure>`).join("");
  if (files.length < 2) $("compare-table").innerHTML = "";
  // a report the server cannot draw (a run still being recorded, a damaged file) showed as a
  // broken image: its one-line reason goes to the messages and the figure's caption instead
  for (const img of $("reports").querySelectorAll("img")) {
    img.onerror = async () => {
      let why = "the report could not be drawn";
      try {
        const res = await fetch(img.src);
        if (!res.ok) why = (await res.text()).trim() || why;
      } catch (err) { /* the server is gone: the generic line */ }
      img.replaceWith(Object.assign(document.createElement("p"), { className: "bad", textContent: why }));
      say(why, false);
    };
  }
}

function table(rows) {
  return `<table>${rows.map((r) => `<tr>${r.map((c, i) => i ? `<td>${esc(c)}</td>` : `<th>${esc(c)}</th>`).join("")}</tr>`).join("")}</table>`;
}

$("compare").onclick = async () => {
  const [a, b] = S.ticked;
  showReports([a, b]);
  try {
    const res = await fetch(`/api/compare?a=${encodeURIComponent(a)}&b=${encodeURIComponent(b)}`);
    if (!res.ok) throw new Error(await res.text());
    const cmp = await res.json();
    const show = (v) => (typeof v === "number" ? fmt(v) : v && typeof v === "object" ? JSON.stringify(v) : v ?? "—");
    if (cmp.kind === "rows") {
      const keys = ["started", "loop", "method", "rule", "ku", "pu", "status", "samples"];
      $("compare-table").innerHTML = table([["", a, b], ...keys.map((k) => [k, show(cmp.rows[0][k]), show(cmp.rows[1][k])])]);
    } else {  // the logger's comparison (autotune runs --compare): a row per figure
      const c = cmp.compare, [ra, rb] = c.runs;
      const run = (r) => `${r.loop} ${r.method} run ${r.run_id} (${(r.started || "").slice(0, 19)})`;
      const cell = (row, v) => (typeof v === "number" && row.key.endsWith("_spread") ? fmt(v, 3) : show(v));  // in % already
      $("compare-table").innerHTML = table([["", `A: ${run(ra)}`, `B: ${run(rb)}`, "B vs A"],
        ...(c.pv_units_differ ? [[`PV units differ (A ${ra.pv_units || "—"}, B ${rb.pv_units || "—"}): figures in PV units are shown, not compared`, "", "", ""]] : []),
        ...c.rows.map((r) => [r.unit ? `${r.label} (${r.unit})` : r.label, cell(r, r.a), cell(r, r.b),
          typeof r.points === "number" ? `${r.points >= 0 ? "+" : ""}${fmt(r.points, 3)} pt`  // figures in %: points
            : r.change === null ? "" : `${r.change >= 0 ? "+" : ""}${(100 * r.change).toFixed(1)} %`])]);
    }
  } catch (err) { say(`compare: ${err}`, false); }
};
$("runs-refresh").onclick = loadRuns;

connect();
loadRuns();
setInterval(loadRuns, 15000);
requestAnimationFrame(frame);
window.addEventListener("resize", () => { S.dirty = true; drawStep(); });
