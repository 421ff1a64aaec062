// motorctl scope: frames of min/max envelopes from the daemon's /ws, drawn with uPlot.
// Read-only: this page sends nothing to the daemon. window.scope is its state (for tests).
"use strict";
const S = window.scope = {frames: 0, dropped: 0, t: [], min: {}, max: {}, meta: null,
                          status: {}, paused: false, armed: "", trigger: null, plots: {}};
const DEFAULT = ["X.e", "X.u", "Y.e", "Y.u"];
const $ = (id) => document.getElementById(id);

function windowS() { return Math.max(0.1, parseFloat($("window").value) || 5); }

function chosen() { return Array.from($("channels").selectedOptions).map((o) => o.value); }

function unitOf(ch) { const m = S.meta; return m ? m.units[m.channels.indexOf(ch)] : ""; }

// what a plot shows: errors in µm (the recorder's unit is m), everything else as recorded
function display(ch) {
  const u = unitOf(ch);
  if (u === "m" && (ch.endsWith(".e"))) return {unit: "µm", scale: 1e6};
  if (u === "m/s" && ch.endsWith(".p")) return {unit: "mm/s", scale: 1e3};
  return {unit: u, scale: 1};
}

function scaled(a, k) { return k === 1 ? a : a.map((v) => (v === null ? null : v * k)); }

function rebuild() {
  const box = $("plots");
  box.innerHTML = "";
  S.plots = {};
  const w = Math.max(400, window.innerWidth - 40);
  for (const ch of chosen()) {
    const div = document.createElement("div");
    div.id = "plot-" + ch;
    box.appendChild(div);
    const opts = {
      title: ch + " [" + display(ch).unit + "]", width: w, height: 170, legend: {show: false},
      scales: {x: {time: false}},
      series: [{label: "t [s]"},
               {label: "max", stroke: "#1f77b4", width: 1},
               {label: "min", stroke: "#1f77b4", width: 1}],
      bands: [{series: [1, 2], fill: "rgba(31,119,180,0.2)"}],
    };
    S.plots[ch] = new uPlot(opts, [[], [], []], div);
  }
}

function trim() {
  const t = S.t;
  if (!t.length) return;
  const keep = t[t.length - 1] - windowS();
  let i = 0;
  while (i < t.length && t[i] < keep) i++;
  if (i > 0) {
    S.t = t.slice(i);
    for (const k in S.min) { S.min[k] = S.min[k].slice(i); S.max[k] = S.max[k].slice(i); }
  }
}

function draw() {
  if (S.paused) return;
  for (const ch in S.plots) {
    const k = display(ch).scale;
    S.plots[ch].setData([S.t, scaled(S.max[ch] || [], k), scaled(S.min[ch] || [], k)]);
  }
}

function showStatus(st) {
  const axes = (st && st.axes) || {};
  let html = "<table><tr><th>axis</th><th>state</th><th>phase</th><th>controller</th><th>latched fault</th></tr>";
  for (const a in axes) {
    const s = axes[a];
    html += "<tr><td>" + a + "</td><td>" + s.state + "</td><td>" + s.phase + "</td><td>" + s.controller +
            "</td><td class='fault' id='fault-" + a + "'>" + (s.fault || "") + "</td></tr>";
  }
  $("axes").innerHTML = html + "</table>";
}

function onFrame(f) {
  S.frames += 1;
  S.t.push(...f.t);
  for (const k in f.min) {
    (S.min[k] = S.min[k] || []).push(...f.min[k]);
    (S.max[k] = S.max[k] || []).push(...f.max[k]);
  }
  for (const ev of f.events) {
    if (S.armed && ev.kind === S.armed && S.trigger === null) {
      S.trigger = ev;
      $("state").textContent = "triggered: " + ev.kind + (ev.axis ? " on " + ev.axis : "") +
                               " at t = " + ev.t.toFixed(4) + " s";
    }
  }
  // single shot: freeze half a window after the trigger
  if (S.trigger && !S.paused && S.t.length && S.t[S.t.length - 1] >= S.trigger.t + windowS() / 2) {
    setPaused(true);
  }
}

function setPaused(p) {
  S.paused = p;
  $("pause").textContent = p ? "run" : "pause";
}

function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.onmessage = (m) => {
    const msg = JSON.parse(m.data);
    if (msg.meta) {
      S.meta = msg.meta;
      const sel = $("channels");
      sel.innerHTML = "";
      for (const ch of msg.meta.channels) {
        const o = document.createElement("option");
        o.value = o.textContent = ch;
        o.selected = DEFAULT.includes(ch);
        sel.appendChild(o);
      }
      rebuild();
      $("state").textContent = "live";
      return;
    }
    if (!S.paused) for (const f of msg.frames) onFrame(f);
    S.status = msg.status;
    showStatus(msg.status);
    S.dropped = msg.dropped || 0;    // frames this page missed (it or the daemon was behind)
    $("dropped").textContent = S.dropped ? S.dropped + " frames dropped" : "";
    trim();
  };
  ws.onclose = () => { $("state").textContent = "disconnected: retrying"; setTimeout(connect, 1000); };
}

$("pause").onclick = () => { setPaused(!S.paused); if (!S.paused) S.trigger = null; };
$("channels").onchange = rebuild;
$("trigger").onchange = () => { S.armed = $("trigger").value; S.trigger = null; setPaused(false);
                                $("state").textContent = S.armed ? "armed: " + S.armed : "live"; };
setInterval(draw, 100);
connect();
