// The EV lab twin's panel: one stream (server-sent events) for state,
// frames and events; REST for commands. See docs/panel-api.md.
"use strict";

const token = new URLSearchParams(location.search).get("token");
const q = token ? "?token=" + encodeURIComponent(token) : "";
const $ = (id) => document.getElementById(id);
const el = (tag, cls, text) => {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
};

let info = { role: "serve", read_only: false };
let last = null;          // the last message
let paused = false;
let frames = [];          // shown frames, newest last
const MAX_FRAMES = 2000;
let trend = [];           // [t, sp, hall, light, wheel]
let lastFrameT = {};      // per link, for Δ
let skipped = 0;

async function api(path, body) {
  const opts = { headers: {} };
  if (token) opts.headers["Authorization"] = "Bearer " + token;
  if (body !== undefined) {
    opts.method = "POST";
    opts.headers["Content-Type"] = "application/json";
    opts.body = JSON.stringify(body);
  }
  const r = await fetch(path, opts);
  const j = await r.json().catch(() => ({}));
  if (!r.ok) throw new Error(j.error || r.status + " " + r.statusText);
  return j;
}

function say(text, bad) {
  const li = el("li", bad ? "bad" : "", text);
  $("events").prepend(li);
  while ($("events").children.length > 200) $("events").lastChild.remove();
}

// A refusal is said beside the control that was refused (an ARIA live
// region, so a screen reader says it too) and kept in the events.
function refuse(where, text) {
  const box = where && $("refusal-" + where);
  if (box) box.textContent = "refused: " + text;
  say("refused: " + text, true);
}
function clearRefusal(where) {
  const box = where && $("refusal-" + where);
  if (box) box.textContent = "";
}
async function send(path, body, where, explain) {
  try {
    const answer = await api(path, body);
    clearRefusal(where);
    return answer;
  } catch (e) {
    refuse(where, e.message + (explain ? " — " + explain : ""));
    return null;
  }
}

// ---- gauges --------------------------------------------------------------
const GAUGES = [
  ["v1", "V1 battery", "V", 0, 50, 2],
  ["v2", "V2 DC bus", "V", 0, 60, 2],
  ["i", "I inverter", "A", -5, 20, 2],
  ["soc", "SOC", "%", 0, 100, 1],
  ["hall", "Hall rpm (RPM_M)", "rpm", 0, 3000, 0],
  ["light", "Light rpm (RPM_L)", "rpm", 0, 3000, 0],
  ["wheel", "True wheel rpm", "rpm", 0, 3000, 0],
];
function buildGauges() {
  const box = $("gauges");
  for (const [id, label, unit, lo, hi] of GAUGES) {
    const g = el("div", "gauge");
    g.id = "g-" + id;
    g.dataset.lo = lo; g.dataset.hi = hi;
    const l = el("div", "label"); l.append(el("span", "", label)); g.append(l);
    const n = el("div"); n.append(el("span", "num", "–"), el("span", "unit", unit)); g.append(n);
    g.append(el("div", "raw", ""));
    const bar = el("div", "bar"); bar.append(el("i")); g.append(bar);
    box.append(g);
  }
}
function gauge(id, value, digits, raw, forced) {
  const g = $("g-" + id);
  if (!g) return;
  const ok = typeof value === "number" && isFinite(value);
  g.querySelector(".num").textContent = ok ? value.toFixed(digits) : "–";
  g.querySelector(".raw").textContent = raw === undefined || raw === null ? "" : raw;
  const lo = +g.dataset.lo, hi = +g.dataset.hi;
  const f = ok ? Math.max(0, Math.min(1, (value - lo) / (hi - lo))) : 0;
  g.querySelector(".bar i").style.width = (f * 100).toFixed(1) + "%";
  g.classList.toggle("forced", !!forced);
}

function renderGauges(m) {
  const st = m.state || {};
  const dev = (st.devices || []).find((d) => d.controller);
  const mod = (st.modules || [])[0];
  if (dev) {
    const c = dev.controller, x = c.inputs, f = c.forced;
    // Where the map places each signal (`at`), or its default block.
    const at = (v, home) => (v.at === undefined ? home : v.at === null ? "not in the map" : v.at);
    const counts = (v) => (v.counts === null || v.counts === undefined ? "–" : v.counts);
    gauge("v1", x.V1.value, 2, counts(x.V1) + " counts (" + at(x.V1, "EA V1") + ")", f.v1 !== null);
    gauge("v2", x.V2.value, 2, counts(x.V2) + " counts (" + at(x.V2, "EA V2") + ")", f.v2 !== null);
    gauge("i", x.I.value, 2, counts(x.I) + " counts (" + at(x.I, "EA I") + ")", f.i !== null);
    gauge("soc", x.SOC.value, 1, counts(x.SOC) + " (" + at(x.SOC, "FA SOC") + ", 0.1 %)");
    gauge("hall", x.RPM_M.value, 0, at(x.RPM_M, "EA RPM_M"), f.rpm_m !== null);
    gauge("light", x.RPM_L.value, 0, at(x.RPM_L, "EA RPM_L") + " · LDR " + counts(x.LDR), f.rpm_l !== null);
  }
  const lp = shownLoop(st);
  if (!dev && lp) {
    gauge("v1", lp.volts.V1, 2, lp.inputs[2] + " counts read");
    gauge("v2", lp.volts.V2, 2, lp.inputs[0] + " counts read");
    gauge("i", lp.volts.I, 2, lp.inputs[1] + " counts read");
    const soc = lp.status.flags ? lp.status.flags[0] / 10 : NaN;
    gauge("soc", soc, 1, "FA SOC as read");
    gauge("hall", lp.inputs[3], 0, "RPM_M as read");
    gauge("light", lp.inputs[4], 0, "RPM_L as read");
  }
  if (mod) gauge("wheel", Math.abs(mod.wheel_rpm), 0, "the plant's wheel");
  else if (lp) gauge("wheel", lp.measured_rpm, 0, "measured by the loop");
  renderLightNote(dev, mod);
  renderStale(st);
}

// The fixed detector loses the flag above a few hundred rpm: light rpm then
// reads 0, which must not look like a stopped wheel.
function renderLightNote(dev, mod) {
  const note = $("light-note");
  const d = dev && dev.controller.light_detector;
  const fixed = d && !d.adaptive;
  note.classList.toggle("hidden", !fixed);
  if (!fixed) return;
  const wheel = mod ? Math.abs(mod.wheel_rpm) : dev.readings ? dev.readings.hall_rpm : 0;
  const beyond = wheel > d.max_rpm;
  note.classList.toggle("warn", beyond);
  note.textContent = "Light rpm: the " + d.description + " detector sees the flag only up to " + d.max_rpm.toFixed(0) + " rpm" +
    (beyond ? "; the wheel turns at " + wheel.toFixed(0) + " rpm, so light rpm reads 0" : "; faster, light rpm reads 0") +
    ". The adaptive detector (VD0 LDR_ADAPT = 1 from a master, or --adaptive-light) follows faster wheels.";
  const g = $("g-light");
  if (g && beyond) g.querySelector(".raw").textContent += " · beyond the fixed detector (" + d.max_rpm.toFixed(0) + " rpm)";
}

// A client panel that lost its slave shows the last values read, and says so.
function renderStale(st) {
  const c = st.connection, note = $("stale-note");
  const stale = !!c && !c.connected;
  $("gauges").classList.toggle("stale", stale);
  note.classList.toggle("hidden", !stale);
  note.classList.toggle("warn", stale);
  if (stale) note.textContent = "Not connected: the values are the last read" +
    (c.last_reply_age_s === null || c.last_reply_age_s === undefined ? "" : ", " + c.last_reply_age_s.toFixed(1) + " s ago") + ", not the module's now.";
}

// The supervisor's slave that the gauges, loop controls and switches show
// and act on: the one chosen, or the first polled.
let loopSlave = null;
function loopsOf(st) {
  const out = [];
  for (const d of (st && st.devices) || []) for (const l of d.loops || []) out.push(l);
  return out;
}
function shownLoop(st) {
  const loops = loopsOf(st);
  return loops.find((l) => l.id === loopSlave) || loops[0] || null;
}
// A control's body names the slave shown, so it acts on that slave only.
function forSlave(body) {
  if (info.role === "supervise" && loopSlave !== null) body.slave = loopSlave;
  return body;
}
const slaveName = (id) => "slave " + String(id).padStart(2, "0");
function chooseSlave(id) {
  if (id === loopSlave) return;
  loopSlave = id;
  // What was typed or being sent belonged to the other slave.
  edited = {}; switchPending = {}; loopPending = false;
  clearRefusal("loop"); clearRefusal("switch");
}
function renderSlaveChoice(m) {
  const loops = loopsOf(m.state);
  const ids = loops.map((l) => l.id);
  if (ids.length && !ids.includes(loopSlave)) loopSlave = ids[0];
  const sel = $("loop-slave");
  if (sel.dataset.ids !== ids.join(",")) {
    sel.replaceChildren(...ids.map((id) => { const o = el("option", "", slaveName(id)); o.value = id; return o; }));
    sel.dataset.ids = ids.join(",");
  }
  if (document.activeElement !== sel && loopSlave !== null) sel.value = loopSlave;
  $("loop-slave-box").classList.toggle("hidden", ids.length < 2);
  $("loop-of").textContent = loopSlave === null ? "" : " · " + slaveName(loopSlave);
}

// ---- outputs, flags, variables ---------------------------------------------
function kv(box, pairs) {
  box.replaceChildren();
  for (const [k, v] of pairs) box.append(el("span", "", k), el("span", "", v));
}
function renderOutputs(m) {
  const st = m.state || {};
  const dev = (st.devices || []).find((d) => d.controller);
  const out = $("outputs");
  out.replaceChildren();
  if (dev) {
    const o = dev.controller.outputs;
    const row = (name, text, sense, lamp) => {
      const r = el("div", "out-row");
      const left = el("span"); const l = el("span", "lamp " + (lamp ? "on" : "off"));
      left.append(l, el("b", "", name + " "), el("span", "sense", sense));
      r.append(left, el("span", "", text));
      out.append(r);
    };
    const where = (v) => (v.at ? " · " + v.at : "");
    const unset = info.role === "client" ? "not written since connecting" : "not set yet";
    row("VEL", o.VEL.counts === null ? unset : o.VEL.value.toFixed(2) + " V (" + o.VEL.counts + " / " + o.VEL.max + ")", "speed command, DAC" + where(o.VEL), o.VEL.counts > 0);
    for (const k of SWITCH_NAMES) {
      const b = o[k];
      const sense = k === "FR" ? "pin 1 = reverse" : "active low";
      row(k, b.on === null ? unset : b.on ? "on" : "off", SWITCH_LABELS[k] + " · " + sense + (b.pin === null ? "" : ": pin " + b.pin) + where(b), b.on);
    }
    drawFlags(dev.controller.status);
    renderPowerUp(dev.controller, st);
    const v = dev.controller.variables;
    if (!v) {
      kv($("variables"), [["ED0 hall code", dev.controller.ED0 === null ? "–" : "0b" + (dev.controller.ED0 >>> 0).toString(2).padStart(4, "0")],
        ["ERRS", String(dev.controller.ERRS)], ["variables", "write-only over MEB (VA, VD): not shown to a client"]]);
    } else kv($("variables"), [["LDR_TH (light threshold)", v.LDR_TH + " counts"], ["RPM_WIN (rpm window)", v.RPM_WIN + " ms"],
      ["LDR_ADAPT (adaptive detector)", v.LDR_ADAPT ? "on" : "off"], ["ED0 hall code", "0b" + (dev.controller.ED0 >>> 0).toString(2).padStart(4, "0")],
      ["ERRS", String(dev.controller.ERRS)]]);
    const forced = Object.entries(dev.controller.forced).filter(([, v]) => v !== null).map(([k, v]) => k + " = " + v);
    $("forced").textContent = forced.length ? "forced: " + forced.join(", ") : "nothing forced";
  }
  const lp = shownLoop(st);
  if (!dev && lp) {
    const r = el("div", "out-row");
    r.append(el("b", "", "VEL written"), el("span", "", lp.vel_written === null ? "–" : lp.vel_written + " counts (PI output " + lp.output + ")"));
    out.append(r);
    kv($("variables"), [["set point", fmt(lp.set_point_rpm, 0) + " rpm"], ["measured", fmt(lp.measured_rpm, 0) + " rpm"],
      ["error", fmt(lp.error_rpm, 0) + " rpm"], ["Kp / Ki", lp.kp + " / " + lp.ki], ["mode", typeof lp.mode === "string" ? "loop" : "manual VEL " + (lp.mode && lp.mode.manual)]]);
    drawFlags(lp.status.lamps, "FD 00 not read yet (status words are polled every few cycles)");
  }
}
// The status word's lamps, each with its word: colour alone is not enough.
function drawFlags(s, missing) {
  const flags = $("flags"); flags.replaceChildren();
  if (!s) { flags.append(el("span", "note", missing || "not read yet")); return; }
  const lamp = (id, name, on, bad, onText, offText) => {
    const w = el("span"); w.id = "flag-" + id; w.dataset.on = on ? "1" : "0";
    w.append(el("span", "lamp " + (on === null ? "off" : on ? (bad ? "bad" : "on") : "off")), name + " ",
      el("span", "lamp-text", on === null ? "?" : on ? onText || "on" : offText || "off"));
    flags.append(w);
  };
  lamp("bms", "BMS cut-off", s.battery_cut_off, true); lamp("oc", "over-current", s.over_current, true);
  lamp("stall", "stall", s.stalled, true); lamp("brake", "brake", s.brake); lamp("charging", "charging", s.charging);
  lamp("ccw", "direction", s.ccw, false, "CCW (reverse)", "CW (forward)");
}
// At power-up SD0 = 0x001F: every pin high. Every active-low switch is off,
// but FR's high pin is reverse: FR reads on and CCW lights while the wheel stands.
function renderPowerUp(c, st) {
  const note = $("powerup-note");
  const frUnwritten = c.sd0 === undefined && c.outputs.FR.on === null;
  const show = (c.sd0 === 0x1f || frUnwritten) && c.status.ccw === true;
  note.classList.toggle("hidden", !show);
  if (show) note.textContent = "FR on and CCW lit" + (frUnwritten ? " (FR not written by this panel)" : "") +
    ": the module's power-up outputs are SD0 = 0x001F, every pin high. The other switches are active low, so high is off, " +
    "but FR's high pin selects reverse: the wheel stands, turned to counter-clockwise, until a master writes SD0.";
}
// ---- the inputs (twin serve): every input set by a slider, a code or a switch
// What each input takes comes from the server (/api/info `inputs`), which
// checks every value again and says its range in a refusal.
let inputEdited = {};
function buildInputs(list) {
  const box = $("inputs-set");
  box.replaceChildren();
  for (const inp of list || []) {
    const n = inp.name;
    const row = el("div", "input-row"); row.id = "in-" + n;
    row.append(el("b", "", n.toUpperCase()), el("span", "what", inp.label));
    const ctl = el("div", "ctl");
    let value;
    const force = (v) => send("/api/force", { input: n, value: v }, "in-" + n).then((a) => { if (a) delete inputEdited[n]; });
    if (inp.kind === "switch") {
      const l = el("label", "switch");
      value = el("input"); value.type = "checkbox";
      l.append(value, n === "flag" ? " in the beam (dark)" : " fault");
      value.onchange = () => { inputEdited[n] = true; force(value.checked); };
      ctl.append(l);
    } else if (inp.kind === "code") {
      value = el("select");
      for (let c = inp.min; c <= inp.max; c++) {
        const o = el("option", "", c + " = " + c.toString(2).padStart(3, "0") + " (C B A)"); o.value = c; value.append(o);
      }
      value.onchange = () => { inputEdited[n] = true; force(+value.value); };
      ctl.append(value);
    } else {
      const slider = el("input"); slider.type = "range"; slider.id = "slider-" + n;
      slider.min = inp.min; slider.max = inp.max; slider.step = inp.step;
      slider.setAttribute("aria-label", n + " slider");
      value = el("input"); value.type = "number"; value.step = "any";
      slider.oninput = () => { inputEdited[n] = true; value.value = slider.value; };
      slider.onchange = () => force(+slider.value);
      value.oninput = () => { inputEdited[n] = true; };
      value.onkeydown = (e) => { if (e.key === "Enter") { e.preventDefault(); set.click(); } };
      ctl.append(slider);
      const set = el("button", "", "Set"); set.type = "button"; set.id = "force-" + n;
      set.onclick = () => {
        const text = value.value.trim();
        // An empty box is no value: said here, the server never sees it.
        if (text === "" || !isFinite(+text)) { refuse("in-" + n, "value: enter a number — " + inp.takes); return; }
        force(+text);
      };
      ctl.append(value, el("span", "unit", inp.unit + " (" + inp.min + " to " + inp.max + ")"), set);
    }
    value.id = "value-" + n;
    value.setAttribute("aria-label", n);
    const release = el("button", "", "Release"); release.type = "button"; release.id = "release-" + n;
    release.onclick = () => send("/api/release", { input: n }, "in-" + n).then(() => { delete inputEdited[n]; });
    ctl.append(release, el("span", "now", ""));
    row.append(ctl);
    const refusal = el("p", "refusal"); refusal.id = "refusal-in-" + n;
    refusal.setAttribute("role", "alert"); refusal.setAttribute("aria-live", "assertive");
    row.append(refusal);
    box.append(row);
  }
}
// Each control shows the value in force: the one set here, else the
// plant's, unless the user is changing it.
function renderInputs(dev, mod) {
  if (!dev) return;
  const c = dev.controller, x = c.inputs, f = c.forced, ed0 = c.ED0 >>> 0;
  const plant = { v1: x.V1.value, v2: x.V2.value, i: x.I.value, rpm_m: x.RPM_M.counts, rpm_l: x.RPM_L.counts,
    ldr: x.LDR.counts, hall: ed0 & 7, flag: (ed0 & 8) !== 0, driver_fault: mod ? !!mod.motor_tripped : null };
  for (const n of Object.keys(plant)) {
    const row = $("in-" + n);
    if (!row) continue;
    const forced = f[n] !== null && f[n] !== undefined;
    const v = forced ? f[n] : plant[n];
    row.classList.toggle("forced", forced);
    const shown = typeof v === "boolean" ? (v ? "on" : "off") : typeof v === "number" ? (Number.isInteger(v) ? String(v) : v.toFixed(2)) : "–";
    row.querySelector(".now").textContent = (forced ? "set: " : "plant: ") + shown;
    const value = $("value-" + n), slider = $("slider-" + n);
    const busy = inputEdited[n] || document.activeElement === value || document.activeElement === slider;
    if (busy || v === null || v === undefined) continue;
    if (value.type === "checkbox") value.checked = !!v;
    else {
      value.value = typeof v === "number" && !Number.isInteger(v) ? v.toFixed(2) : v;
      if (slider) slider.value = v;
    }
  }
}

// ---- the module's device number and I/O map (twin serve) ------------------
let mapEdited = false;
function renderSlave(m) {
  const dev = ((m.state && m.state.devices) || []).find((d) => d.slave);
  const card = $("slave-card");
  if (!dev) {
    $("slave-now").textContent = "Set at start: this session's controller keeps its own (compiled firmware, or only --modbus8 nodes).";
    card.querySelectorAll("input, textarea, button").forEach((e) => { e.disabled = true; });
    return;
  }
  const s = dev.slave;
  $("slave-now").textContent = "The module answers as slave " + String(s.id).padStart(2, "0") + ", " +
    (s.map_is_default ? "with the default I/O map (docs/protocols/meb.md)" : "with the I/O map below") + ".";
  if (document.activeElement !== $("slave-id") && !inputEdited.slaveId) $("slave-id").value = s.id;
  if (document.activeElement !== $("slave-map") && !mapEdited) $("slave-map").value = s.map;
}
const SWITCH_NAMES = ["EN", "BRK", "PRO", "DES", "FR", "CHG"];
const SWITCH_LABELS = { EN: "inverter enable", BRK: "brake", PRO: "converter boost", DES: "bus bleeder", FR: "reverse", CHG: "charger" };

// ---- the switches (twin panel, twin supervise in manual mode) --------------
let switchPending = {};
function buildSwitches() {
  const box = $("switches");
  for (const k of SWITCH_NAMES) {
    const l = el("label");
    const c = el("input"); c.type = "checkbox"; c.id = "sw-" + k;
    c.onchange = async () => {
      switchPending[k] = true;
      const body = {}; body[k] = c.checked;
      await send("/api/outputs", forSlave(body), "switch");
      delete switchPending[k];
    };
    l.append(c, el("b", "", k), el("span", "at", SWITCH_LABELS[k]));
    box.append(l);
  }
}
function renderSwitches(m) {
  let states = null, locked = null;
  if (info.role === "client") {
    const dev = ((m.state && m.state.devices) || []).find((d) => d.controller);
    if (dev) states = dev.controller.outputs;
    const ov = $("out-vel"), vel = states && states.VEL.counts;
    if (states && document.activeElement !== ov) {
      ov.value = vel === null ? 0 : vel;
      $("out-vel-out").textContent = vel === null ? "not written since connecting" : vel;
    }
  } else if (info.role === "supervise") {
    const lp = shownLoop(m.state);
    if (lp) {
      states = (m.switches || {})[String(lp.id)] || null;
      if (lp.mode === "loop") locked = "the loop is on: switch it off (manual VEL) to set the switches";
    }
  }
  for (const k of SWITCH_NAMES) {
    const c = $("sw-" + k);
    c.disabled = !!locked;
    if (states && states[k] && !switchPending[k]) {
      // Unknown (not written since connecting): neither ticked nor not.
      c.indeterminate = states[k].on === null;
      c.checked = states[k].on === true;
    }
  }
  $("switch-note").textContent = locked || "On: the lab's active sense (pin 0), but FR: on is reverse (pin 1). MEB outputs cannot be read back: shown as last set here.";
}
function renderConnection(m) {
  const c = m.state && m.state.connection;
  const b = $("conn");
  b.classList.toggle("hidden", !c);
  if (!c) return;
  b.className = "badge " + (c.connected ? "" : "bad");
  b.id = "conn";
  b.textContent = c.connected ? "MEB client of " + c.url + " · slave " + String(c.id).padStart(2, "0") + (c.error ? " · " + c.error : "")
    : "disconnected from " + c.url + ": " + (c.error || "?") + " · retrying";
}
const fmt = (v, d) => (typeof v === "number" && isFinite(v) ? v.toFixed(d) : "–");

// ---- supervise: per-slave lights --------------------------------------------
// Exchanges and failures per slave over the last few seconds: a lamp shows
// the recent state, so one timeout long ago does not keep it amber, and a
// loaded machine's odd timeout does not either (amber past one in five).
const RECENT_S = 5;
let slaveHistory = {};
function recentFailures(id, t, failed, requests) {
  const h = (slaveHistory[id] = slaveHistory[id] || []);
  h.push([t, failed, requests]);
  while (h.length > 1 && h[1][0] <= t - RECENT_S) h.shift();
  return [failed - h[0][1], requests - h[0][2]];
}
function renderSlaves(m) {
  const box = $("loop-slaves");
  const shown = new Set();
  for (const l of loopsOf(m.state)) {
    const age = l.measured_at === null ? null : m.t - l.measured_at;
    const c = l.counters;
    // A row lasts while its slave is polled, so a click on it is not lost
    // to a redraw between the press and the release.
    let r = box.querySelector('.out-row[data-id="' + l.id + '"]');
    if (!r) {
      r = el("div", "out-row"); r.dataset.id = l.id; r.title = "show and set this slave's loop";
      r.onclick = () => chooseSlave(l.id);
      box.append(r);
    }
    r.classList.toggle("chosen", l.id === loopSlave);
    shown.add(String(l.id));
    const left = el("span");
    const [failed, asked] = recentFailures(l.id, m.t, c.bad_checks + c.timeouts + c.exceptions, c.requests);
    const share = failed ? " (" + failed + " of " + asked + " exchanges failed in the last " + RECENT_S + " s)" : "";
    const [lampCls, word] = age === null ? ["bad", "no reply yet"] : age > 1 ? ["bad", "no reply for " + age.toFixed(1) + " s"]
      : failed * 5 > asked ? ["warn", "replying, with failures" + share] : ["on", "replying" + share];
    left.dataset.state = lampCls;
    left.append(el("span", "lamp " + lampCls), el("b", "", slaveName(l.id) + " "), el("span", "lamp-text", word));
    left.id = "slave-" + l.id;
    left.dataset.badChecks = c.bad_checks; left.dataset.timeouts = c.timeouts;
    r.replaceChildren(left, el("span", "", "timeouts " + c.timeouts + " · bad checks " + c.bad_checks + " · last reply " + (age === null ? "never" : (age * 1000).toFixed(0) + " ms ago")));
  }
  for (const r of [...box.children]) if (!shown.has(r.dataset.id)) r.remove();
}

// ---- links and faults -------------------------------------------------------
let faultsBuilt = "";
// On a phone a table's rows are stacked, each cell under its column's name
// (panel.css): the names come from the table's own header.
const columnNames = {};
function labelCells(tr, table) {
  const names = (columnNames[table] = columnNames[table] || [...$(table).querySelectorAll("thead th")].map((th) => th.textContent));
  [...tr.cells].forEach((td, i) => { td.dataset.label = names[i] || ""; });
}
function renderLinks(m) {
  const tb = $("links").querySelector("tbody");
  tb.replaceChildren();
  const st = m.state || {};
  const names = [];
  for (const l of st.links || []) {
    names.push(l.name);
    const s = (m.links || {})[l.name] || {};
    const tr = el("tr");
    const age = s.last_frame_age_s;
    const [lampCls, word] = linkLamp(s, age);
    const lampTd = el("td"); lampTd.id = "lamp-" + l.name; lampTd.dataset.state = lampCls;
    lampTd.append(el("span", "lamp " + lampCls), el("span", "lamp-text", word));
    tr.append(lampTd, el("td", "", l.name), el("td", "", l.address), el("td", "", String(l.clients)),
      el("td", "", String(s.frames_in || 0)), el("td", "", String(s.frames_out || 0)), el("td", "", String(s.errors || 0)),
      el("td", "", age === null || age === undefined ? "never" : age < 1 ? (age * 1000).toFixed(0) + " ms ago" : age.toFixed(1) + " s ago"));
    labelCells(tr, "links");
    tb.append(tr);
  }
  const key = names.join(",");
  if (key !== faultsBuilt) { buildFaults(names); buildLinkFilter(names); faultsBuilt = key; }
  const f = st.fault;
  $("fault-badge").classList.toggle("hidden", !f);
  if (f) $("fault-badge").textContent = "fault " + f.fault + " on " + (f.link || "every link");
  document.querySelectorAll("#faults button[data-fault]").forEach((b) => {
    const on = f && f.fault.startsWith(b.dataset.fault) && (f.link === b.dataset.link || f.link === null);
    b.classList.toggle("on", !!on);
  });
}
// Red: frames fail their check and none has passed for a second; amber:
// errors among good frames, or a quiet link. Errors count over the last 5 s.
function linkLamp(s, age) {
  if (age === null || age === undefined) return ["off", "no frames yet"];
  const good = s.last_good_age_s;
  if (s.errors_recent && (good === null || good === undefined || good > 1))
    return ["bad", s.errors_recent + " errors, no good frame " + (good === null || good === undefined ? "yet" : "for " + good.toFixed(1) + " s")];
  if (s.errors_recent) return ["warn", s.errors_recent + " errors in the last 5 s"];
  if (age >= 1) return ["warn", "quiet for " + age.toFixed(1) + " s"];
  return ["on", "ok"];
}
function buildFaults(names) {
  const box = $("faults");
  box.replaceChildren();
  for (const name of names) {
    const r = el("div", "fault-row");
    r.append(el("b", "", name));
    const code = el("select"); code.id = "fault-code-" + name; code.setAttribute("aria-label", "exception code");
    for (const [n, what] of [[1, "illegal command"], [2, "illegal address"], [3, "illegal data"], [4, "device failure"]]) {
      const o = el("option", "", "0" + n + " " + what); o.value = n; code.append(o);
    }
    code.value = 4;
    for (const [kind, label] of [["bad-check", "bad check"], ["no-reply", "no reply"], ["exception", "exception"]]) {
      const b = el("button", "", label);
      b.dataset.fault = kind; b.dataset.link = name;
      b.id = "fault-" + kind + "-" + name;
      b.onclick = () => send("/api/fault", kind === "exception" ? { fault: kind, link: name, code: +code.value } : { fault: kind, link: name }, "fault");
      if (kind === "exception") r.append(code);
      r.append(b);
    }
    const ms = el("input"); ms.type = "number"; ms.value = 50; ms.min = 0; ms.max = 60000; ms.style.width = "5rem";
    ms.setAttribute("aria-label", "delay ms");
    const d = el("button", "", "delay ms");
    d.dataset.fault = "delay"; d.dataset.link = name;
    d.onclick = () => send("/api/fault", { fault: "delay", link: name, delay_ms: +ms.value }, "fault", "the delay takes 0 to 60000 ms");
    // A reply as another slave's (the id next to its own unless one is given).
    const id = el("input"); id.type = "number"; id.min = 1; id.max = 247; id.placeholder = "next";
    id.style.width = "4rem"; id.id = "fault-id-" + name; id.setAttribute("aria-label", "wrong id");
    const w = el("button", "", "wrong id");
    w.dataset.fault = "wrong-id"; w.dataset.link = name; w.id = "fault-wrong-id-" + name;
    w.onclick = () => send("/api/fault", id.value === "" ? { fault: "wrong-id", link: name } : { fault: "wrong-id", link: name, id: +id.value }, "fault", "the id takes 1 to 247");
    // Each reply in two writes, this many ms apart.
    const gap = el("input"); gap.type = "number"; gap.value = 5; gap.min = 0; gap.max = 10000;
    gap.style.width = "4rem"; gap.id = "fault-gap-" + name; gap.setAttribute("aria-label", "split gap ms");
    const sp = el("button", "", "split, gap ms");
    sp.dataset.fault = "split"; sp.dataset.link = name; sp.id = "fault-split-" + name;
    sp.onclick = () => send("/api/fault", { fault: "split", link: name, gap_ms: +gap.value }, "fault", "the gap takes 0 to 10000 ms");
    // Junk: a count of random bytes, or hex bytes; before or after each reply.
    const junk = el("input"); junk.value = "3"; junk.style.width = "5rem"; junk.id = "fault-junk-bytes-" + name;
    junk.setAttribute("aria-label", "junk: count or hex bytes (hex:00ff)");
    const place = el("select"); place.id = "fault-junk-place-" + name; place.setAttribute("aria-label", "junk place");
    for (const p of ["before", "after"]) { const o = el("option", "", p); o.value = p; place.append(o); }
    const j = el("button", "", "junk");
    j.dataset.fault = "junk"; j.dataset.link = name; j.id = "fault-junk-" + name;
    j.onclick = () => {
      const v = junk.value.trim();
      const what = v.startsWith("hex:") ? { junk_hex: v.slice(4) } : { junk_count: +v };
      send("/api/fault", Object.assign({ fault: "junk", link: name, junk_place: place.value }, what), "fault",
        "junk takes a count (1 to 32) or hex:BYTES");
    };
    const off = el("button", "", "off");
    off.id = "fault-off-" + name;
    off.onclick = () => send("/api/fault", { fault: "off" }, "fault");
    r.append(ms, d, id, w, gap, sp, junk, place, j, off);
    box.append(r);
  }
}
function buildLinkFilter(names) {
  const s = $("filter-link");
  const keep = s.value;
  s.replaceChildren(el("option", "", "all links"));
  s.firstChild.value = "";
  for (const n of names) { const o = el("option", "", n); o.value = n; s.append(o); }
  s.value = keep;
}

// ---- frame monitor ----------------------------------------------------------
function frameNode(f) {
  const d = f.decoded || {};
  return d.id !== undefined ? String(d.id) : d.unit !== undefined ? String(d.unit) : "";
}
function decodedText(f) {
  const d = f.decoded || {};
  if (d.error) return "✗ " + d.error;
  return Object.entries(d).filter(([k]) => k !== "protocol").map(([k, v]) => k + " " + (Array.isArray(v) ? v.join(",") : v)).join(" · ");
}
function matches(f) {
  const link = $("filter-link").value, node = $("filter-node").value.trim().toLowerCase();
  if (link && f.link !== link) return false;
  if (!node) return true;
  return frameNode(f) === node.replace(/^0+(?=\d)/, "") || f.text.toLowerCase().includes(node) || (f.from || "").includes(node) || (f.to || "").includes(node);
}
function takeFrames(list) {
  for (const f of list) {
    const prev = lastFrameT[f.link];
    f.gap_ms = prev === undefined ? null : (f.t - prev) * 1000;
    lastFrameT[f.link] = f.t;
    frames.push(f);
  }
  if (frames.length > MAX_FRAMES) frames.splice(0, frames.length - MAX_FRAMES);
}
function renderFrames() {
  const tb = $("frames").querySelector("tbody");
  const shown = frames.filter(matches).slice(-200).reverse();
  const rows = shown.map((f) => {
    const tr = el("tr", (f.bad ? "bad " : "") + f.dir);
    tr.append(el("td", "", f.t.toFixed(4)), el("td", "", f.gap_ms === null ? "" : f.gap_ms.toFixed(1)), el("td", "", f.link),
      el("td", "dir", f.from + " → " + f.to), el("td", "text", f.text), el("td", "dec", decodedText(f)));
    labelCells(tr, "frames");
    return tr;
  });
  tb.replaceChildren(...rows);
  renderScope(last);
  $("frame-count").textContent = frames.length + " kept" + (skipped ? ", " + skipped + " skipped (faster than the panel)" : "") + (paused ? " · paused" : "");
}
function exportCsv() {
  const esc = (s) => '"' + String(s).replace(/"/g, '""') + '"';
  const lines = ["t_s,end_s,link,direction,from,to,frame,decoded,bad"];
  for (const f of frames.filter(matches))
    lines.push([f.t, f.end, f.link, f.dir, esc(f.from), esc(f.to), esc(f.text), esc(decodedText(f)), f.bad].join(","));
  const a = el("a");
  a.href = URL.createObjectURL(new Blob([lines.join("\n") + "\n"], { type: "text/csv" }));
  a.download = "frames.csv";
  document.body.append(a); a.click(); a.remove();
}

// ---- scope ------------------------------------------------------------------
// The last few frames of one link as a scope shows its lines: every byte as
// its UART bits (start bit low, data bits LSB first, parity, stop bits high)
// at the link's baud, the twin's TX on the upper trace and the other side's
// on the lower, each frame at its recorded time, its bytes in hex under it.
// A quiet line longer than a few characters is cut, and the cut says how
// long it was: at true scale a 100 ms wait would leave the bytes no width.
const SVG = "http://www.w3.org/2000/svg";
const SCOPE_CUT_CHARS = 4;        // quiet longer than this many characters is cut
const SCOPE_CUT_PX = 44;          // the width of a cut
const SCOPE_LANES = { out: [18, 44, 58], in: [82, 108, 122] };  // high, low, hex line
function svgEl(tag, attrs, text) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}
// A frame's bytes: its hex, or (a text frame) the hex the stream adds.
function frameBytes(f) {
  const hex = f.hex || f.text;
  return hex.split(" ").filter((h) => h).map((h) => parseInt(h, 16));
}
// The levels of one character, 1 high: start, data LSB first, parity, stop.
function charBits(byte, line) {
  const bits = [0];
  let ones = 0;
  for (let i = 0; i < line.data_bits; i++) { const b = (byte >> i) & 1; bits.push(b); ones += b; }
  if (line.parity === "E") bits.push(ones & 1);
  if (line.parity === "O") bits.push((ones & 1) ^ 1);
  for (let i = 0; i < line.stop_bits; i++) bits.push(1);
  return bits;
}
function renderScope(m) {
  const box = $("scope");
  const W = Math.max(box.clientWidth || 0, 200), H = 150, L = 62, R = 6;
  box.setAttribute("viewBox", "0 0 " + W + " " + H);
  const kept = frames.filter(matches);
  const link = $("filter-link").value || (kept.length ? kept[kept.length - 1].link : "");
  // Two frames on a phone (a request and its reply), four on a wider screen.
  const shown = kept.filter((f) => f.link === link).slice(W < 600 ? -2 : -4);
  const info = ((m && m.state && m.state.links) || []).find((l) => l.name === link) || {};
  const line = info.line || { baud: 115200, data_bits: 8, parity: "N", stop_bits: 1 };
  const perChar = 1 + line.data_bits + (line.parity === "N" ? 0 : 1) + line.stop_bits;
  const bitS = 1 / line.baud;
  box.dataset.link = link;
  box.dataset.baud = line.baud;
  $("scope-of").textContent = link ? "· " + link : "";
  $("scope-note").textContent = !link ? "" :
    (info.line ? "" : "A TCP link has no line: drawn as on a serial line at 115200 baud 8N1. ") +
    line.baud + " baud " + line.data_bits + line.parity + line.stop_bits + ", one bit " + (bitS * 1e6).toFixed(2) +
    " µs; quiet longer than " + SCOPE_CUT_CHARS + " characters is cut (the cut gives its length).";
  // Said below once the frames are placed.
  const said = $("scope-note").textContent;
  const parts = [];
  for (const [dir, [hi, lo]] of Object.entries(SCOPE_LANES)) {
    const who = dir === "out" ? "twin" : ((shown.filter((f) => f.dir === "in").pop() || {}).from || "other side");
    parts.push(svgEl("text", { class: "lane", x: 2, y: (hi + lo) / 2 + 4 }, who + " TX"));
  }
  // Segments of frames close in time; a cut between them. A line carries
  // one frame at a time: one recorded as starting before the last on its
  // side had ended (a pseudo-terminal carries bytes faster than the baud)
  // is drawn after it.
  const segs = [], sideEnd = {};
  let queued = 0;
  for (const f of [...shown].sort((a, b) => a.t - b.t)) {
    const bytes = frameBytes(f), len = bytes.length * perChar * bitS;
    const at = Math.max(f.t, sideEnd[f.dir] ?? -Infinity);
    if (at > f.t) queued++;
    sideEnd[f.dir] = at + len;
    const seg = segs[segs.length - 1];
    if (seg && at - seg.end <= SCOPE_CUT_CHARS * perChar * bitS) {
      seg.frames.push([f, bytes, at]); seg.end = Math.max(seg.end, at + len);
    } else segs.push({ start: at, end: at + len, frames: [[f, bytes, at]] });
  }
  const pad = perChar * bitS;  // a character of idle line either side
  const span = segs.reduce((a, s) => a + (s.end - s.start) + 2 * pad, 0);
  const scale = span > 0 ? (W - L - R - SCOPE_CUT_PX * Math.max(segs.length - 1, 0)) / span : 0;
  let x = L;
  segs.forEach((seg, i) => {
    if (i > 0) {
      const gap = seg.start - segs[i - 1].end;
      parts.push(svgEl("line", { class: "cut", x1: x + SCOPE_CUT_PX / 2, y1: 10, x2: x + SCOPE_CUT_PX / 2, y2: 128 }));
      parts.push(svgEl("text", { x: x + 2, y: 140 }, gap >= 1 ? gap.toFixed(2) + " s" : (gap * 1e3).toFixed(gap < 0.01 ? 2 : 1) + " ms"));
      x += SCOPE_CUT_PX;
    }
    const x0 = x, w = (seg.end - seg.start + 2 * pad) * scale;
    for (const [hi] of Object.values(SCOPE_LANES)) parts.push(svgEl("path", { class: "idle", d: "M" + x0.toFixed(1) + " " + hi + "H" + (x0 + w).toFixed(1) }));
    parts.push(svgEl("text", { x: x0, y: 148 }, seg.start.toFixed(4) + " s"));
    for (const [f, bytes, at] of seg.frames) {
      const [hi, lo, hexY] = SCOPE_LANES[f.dir === "out" ? "out" : "in"];
      const bw = bitS * scale, fx = x0 + (at - seg.start + pad) * scale;
      let d = "M" + fx.toFixed(2) + " " + hi, level = 1, k = 0;
      for (const b of bytes) for (const bit of charBits(b, line)) {
        if (bit !== level) { d += "H" + (fx + k * bw).toFixed(2) + "V" + (bit ? hi : lo); level = bit; }
        k++;
      }
      d += "H" + (fx + k * bw).toFixed(2);
      parts.push(svgEl("path", { class: "bits " + (f.dir === "out" ? "out" : "in") + (f.bad ? " bad" : ""), d,
        "data-t": f.t, "data-x0": fx.toFixed(2), "data-bit": bw.toFixed(4), "data-high": hi, "data-low": lo,
        "data-chars": bytes.length, "data-bits-per-char": perChar }));
      // Each byte's hex under its bits, where there is room; else the frame's start.
      const charPx = perChar * bw;
      if (charPx >= 15) bytes.forEach((b, j) => parts.push(svgEl("text", { class: "byte " + f.dir,
        x: (fx + (j + 0.5) * charPx).toFixed(1), y: hexY, "text-anchor": "middle" }, b.toString(16).toUpperCase().padStart(2, "0"))));
      else {
        // 10 px monospace: a byte's "XX " is 18 px; leave room for the "…".
        const room = Math.floor((bytes.length * charPx + 6) / 18);
        const fit = Math.max(1, room >= bytes.length ? bytes.length : room - 1);
        const hex = bytes.slice(0, fit).map((b) => b.toString(16).toUpperCase().padStart(2, "0")).join(" ");
        parts.push(svgEl("text", { class: "byte " + f.dir, x: fx.toFixed(1), y: hexY }, hex + (fit < bytes.length ? " …" : "")));
      }
    }
    x += w;
  });
  box.replaceChildren(...parts);
  if (queued) $("scope-note").textContent = said + " " + queued + (queued > 1 ? " frames" : " frame") +
    " recorded as starting before the one before on the same side had ended: drawn after it.";
}

// ---- trend ------------------------------------------------------------------
const COLORS = ["--sp", "--hall", "--light", "--wheel"].map((v) => getComputedStyle(document.documentElement).getPropertyValue(v).trim());
function drawTrend() {
  const c = $("trend");
  const w = c.clientWidth, h = c.clientHeight;
  if (c.width !== w * devicePixelRatio) { c.width = w * devicePixelRatio; c.height = h * devicePixelRatio; }
  const g = c.getContext("2d");
  g.setTransform(devicePixelRatio, 0, 0, devicePixelRatio, 0, 0);
  g.clearRect(0, 0, w, h);
  if (!trend.length) return;
  const tEnd = trend[trend.length - 1][0], t0 = tEnd - 30;
  let hi = 100;
  for (const p of trend) for (let k = 1; k < 5; k++) if (p[k] !== null && p[k] > hi) hi = p[k];
  hi = Math.ceil(hi * 1.1 / 100) * 100;
  const L = 44, B = 18;
  const x = (t) => L + (t - t0) / 30 * (w - L - 4), y = (v) => (h - B) - v / hi * (h - B - 6);
  g.strokeStyle = "#2c3540"; g.fillStyle = "#8b98a5"; g.font = "11px system-ui"; g.lineWidth = 1;
  for (let i = 0; i <= 4; i++) {
    const v = hi * i / 4; g.beginPath(); g.moveTo(L, y(v)); g.lineTo(w, y(v)); g.stroke();
    g.fillText(v.toFixed(0), 2, y(v) + 4);
  }
  for (let s = 0; s <= 30; s += 10) g.fillText("-" + (30 - s) + " s", x(t0 + s) - 12, h - 4);
  for (let k = 1; k < 5; k++) {
    g.strokeStyle = COLORS[k - 1]; g.lineWidth = k === 1 ? 2 : 1.5; g.beginPath();
    let pen = false;
    for (const p of trend) {
      if (p[0] < t0 || p[k] === null) { pen = false; continue; }
      if (pen) g.lineTo(x(p[0]), y(p[k])); else g.moveTo(x(p[0]), y(p[k]));
      pen = true;
    }
    g.stroke();
  }
}

// ---- the stream -------------------------------------------------------------
let dirty = false;
function onMessage(m) {
  if (!m.state) return;
  last = m;
  skipped = m.skipped_frames || 0;
  if (!paused) takeFrames(m.frames || []);
  for (const e of m.events || []) say(e.t.toFixed(3) + " s " + e.node + ": " + e.kind + " " + e.detail, /trip|timeout|bad/.test(e.kind));
  const st = m.state, lp = shownLoop(st), dev = (st.devices || []).find((d) => d.readings), mod = (st.modules || [])[0];
  trend.push([m.t, lp ? lp.set_point_rpm : null,
    dev ? dev.readings.hall_rpm : lp ? lp.inputs[3] : null,
    dev ? dev.readings.light_rpm : lp ? lp.inputs[4] : null,
    mod ? Math.abs(mod.wheel_rpm) : lp ? lp.measured_rpm : null]);
  while (trend.length && trend[0][0] < m.t - 31) trend.shift();
  if (!dirty) { dirty = true; requestAnimationFrame(render); }
}
function render() {
  dirty = false;
  const m = last;
  if (!m) return;
  $("clock").textContent = "t = " + m.t.toFixed(1) + " s";
  renderSlaveChoice(m); renderGauges(m); renderOutputs(m); renderLinks(m); renderSlaves(m);
  if (info.role === "serve") {
    const st = m.state || {};
    renderInputs((st.devices || []).find((d) => d.controller), (st.modules || [])[0]);
    renderSlave(m);
  }
  if (info.role !== "serve") { renderSwitches(m); renderConnection(m); }
  if (!paused) renderFrames();
  drawTrend();
  const lp = shownLoop(m.state);
  if (lp) renderLoopControls(lp);
}

// Every loop control shows what the supervisor holds now, unless the user
// is changing it (focused, or edited and not yet sent).
let edited = {};
let loopPending = false;
function renderLoopControls(lp) {
  const shows = (id, value, text) => {
    const e = $(id);
    if (document.activeElement === e || edited[id]) return;
    e.value = value;
    if (text) $(text).textContent = e.value;
  };
  shows("set-point", lp.set_point_rpm || 0, "sp-out");
  shows("kp", lp.kp === null ? "" : lp.kp);
  shows("ki", lp.ki === null ? "" : lp.ki);
  const manual = lp.mode && typeof lp.mode === "object" ? lp.mode.manual : null;
  shows("vel", manual !== null ? manual : lp.vel_written === null ? lp.output : lp.vel_written, "vel-out");
  if (!loopPending) $("loop-on").checked = lp.mode === "loop";
  $("vel").disabled = lp.mode === "loop";
  $("loop-mode").textContent = lp.mode === "loop" ? "the loop sets VEL" : manual !== null ? "manual: VEL held at " + manual + " counts" : "";
}
function connect() {
  const es = new EventSource("/api/stream" + q);
  es.addEventListener("update", (e) => {
    $("live").className = "lamp on"; $("live-text").textContent = "live";
    try { onMessage(JSON.parse(e.data)); } catch (err) { console.error(err); }
  });
  es.addEventListener("lagged", (e) => say("this page missed " + e.data + " updates (slow device or network)", true));
  es.onerror = () => { $("live").className = "lamp bad"; $("live-text").textContent = "reconnecting…"; };
}

// ---- controls ---------------------------------------------------------------
function wire() {
  $("release-all").onclick = () => send("/api/release", { input: "all" }, "force").then(() => { inputEdited = {}; });
  $("slave-id").oninput = () => { inputEdited.slaveId = true; };
  $("slave-id").onkeydown = (e) => { if (e.key === "Enter") { e.preventDefault(); $("slave-id-set").click(); } };
  $("slave-id-set").onclick = async () => {
    const text = $("slave-id").value.trim();
    if (text === "" || !isFinite(+text)) { refuse("slave-id", "id: enter a number from 1 to 99"); return; }
    if (await send("/api/slave", { id: +text }, "slave-id")) delete inputEdited.slaveId;
  };
  $("slave-map").oninput = () => { mapEdited = true; };
  $("slave-map-set").onclick = async () => {
    if (await send("/api/slave", { map: $("slave-map").value }, "slave-map")) mapEdited = false;
  };
  $("slave-map-default").onclick = async () => {
    if (await send("/api/slave", { map: "" }, "slave-map")) mapEdited = false;
  };
  $("pause").onclick = () => { paused = !paused; $("pause").textContent = paused ? "Resume" : "Pause"; $("pause").classList.toggle("on", paused); renderFrames(); };
  $("csv").onclick = exportCsv;
  $("filter-link").onchange = renderFrames;
  $("filter-node").oninput = renderFrames;
  const sp = $("set-point");
  sp.oninput = () => { $("sp-out").textContent = sp.value; };
  sp.onchange = () => send("/api/loop", forSlave({ set_point_rpm: +sp.value }), "loop");
  $("loop-slave").onchange = () => chooseSlave(+$("loop-slave").value);
  // Typed into, cleared or changed by any means: the box is the user's until sent.
  for (const id of ["kp", "ki"]) { $(id).oninput = () => { edited[id] = true; }; $(id).onchange = $(id).oninput; }
  $("gains").onclick = async () => {
    // Only the gains typed in are sent; an empty box is refused here, not sent as 0.
    const body = {};
    for (const id of ["kp", "ki"]) {
      if (!edited[id]) continue;
      const text = $(id).value.trim();
      if (text === "" || !isFinite(+text)) { refuse("loop", (id === "kp" ? "Kp" : "Ki") + ": enter a number from 0 to 1000"); return; }
      body[id] = +text;
    }
    if (!Object.keys(body).length) { refuse("loop", "nothing to set: type a new Kp or Ki first"); return; }
    if (await send("/api/loop", forSlave(body), "loop", "gains take 0 to 1000")) { delete edited.kp; delete edited.ki; }
  };
  $("loop-on").onchange = async () => {
    // Off holds the VEL the slave has (as a client's VD 10 0 does): a
    // turning wheel keeps turning until the manual VEL is moved.
    loopPending = true;
    await send("/api/loop", forSlave({ mode: $("loop-on").checked ? "loop" : "manual" }), "loop");
    loopPending = false;
  };
  const ov = $("out-vel");
  ov.oninput = () => { $("out-vel-out").textContent = ov.value; };
  ov.onchange = () => send("/api/outputs", { vel: +ov.value }, "switch");
  const vel = $("vel");
  vel.oninput = () => { $("vel-out").textContent = vel.value; edited.vel = true; };
  vel.onchange = async () => {
    if (!$("loop-on").checked) await send("/api/loop", forSlave({ mode: "manual", vel: +vel.value }), "loop");
    delete edited.vel;
  };
  $("step").onclick = async () => {
    $("step").disabled = true; kv($("step-result"), [["step", "running…"]]);
    try {
      const r = await api("/api/step", forSlave({ to_rpm: +$("step-to").value, seconds: +$("step-s").value }));
      const rows = [["from → to", fmt(r.from_rpm, 0) + " → " + fmt(r.to_rpm, 0) + " rpm"],
        ["measurements", r.samples + ", largest gap " + fmt(r.largest_gap_ms, 0) + " ms" + (r.largest_gap_ms > 50 ? " (a busy machine: polls were late)" : "")]];
      for (const [name, s] of Object.entries(r.signals)) {
        if (s.error) { rows.push([name, s.error]); continue; }
        const mm = s.metrics;
        rows.push([name + " rise", fmt(mm.rise_time_s, 3) + " s"], [name + " overshoot", fmt(mm.overshoot_pct, 1) + " %"],
          [name + " settling", fmt(mm.settling_time_s, 3) + " s"], [name + " steady error", fmt(mm.steady_state_error, 1) + " rpm"]);
        if (s.delay_s !== undefined && s.delay_s !== null) rows.push([name + " delay", fmt(s.delay_s * 1000, 0) + " ms"]);
      }
      if (r.loop_closes_on) rows.push(["loop", "closes on the " + r.loop_closes_on + " (its figures above)"]);
      kv($("step-result"), rows);
      clearRefusal("loop");
    } catch (e) { kv($("step-result"), []); refuse("loop", "step: " + e.message); }
    $("step").disabled = false;
  };
}

async function start() {
  buildGauges();
  buildSwitches();
  try { info = await api("/api/info"); } catch (e) { say("cannot reach the twin: " + e.message, true); }
  if (info.role === "serve") buildInputs(info.inputs);
  // The title and heading (module and role) come with the page itself.
  // A card shows if one of its roles is this panel's (and it can change things).
  document.querySelectorAll(".control").forEach((e) => {
    const roles = ["serve", "supervise", "client"].filter((r) => e.classList.contains(r + "-only"));
    e.classList.toggle("hidden", !roles.includes(info.role) || info.read_only);
  });
  document.querySelectorAll(".slider.client-only").forEach((e) => e.classList.toggle("hidden", info.role !== "client"));
  if (info.role === "client") {
    $("outputs-card").querySelector("h2").textContent = "Outputs this panel set";
    $("g-wheel").classList.add("hidden");
    // A client reads neither the master's set point nor the true wheel.
    document.querySelectorAll(".legend .sp, .legend .wheel").forEach((e) => e.classList.add("hidden"));
  }
  $("ro").classList.toggle("hidden", !info.read_only);
  if (info.role === "supervise") {
    $("outputs-card").querySelector("h2").textContent = "Master's outputs";
    // A supervisor has no plant: its "wheel" is the reading the loop closes on.
    $("g-wheel").querySelector(".label span").textContent = "Loop's measurement";
    $("legend-wheel").textContent = "loop's measurement (a reading, not the true wheel)";
  }
  try { const t = await api("/api/trend?seconds=30"); trend = t.rows; } catch (e) { /* the stream fills it */ }
  wire();
  connect();
  addEventListener("resize", drawTrend);
}
start();
