// The operator page (docs/operator-page.md): the DRO polled from /operator/status, commands
// POSTed to /operator/cmd/<name> and /operator/program with the session's CSRF token. The
// server decides what is allowed (403 without an operator's session); the page only disables
// what it would be refused.
"use strict";

const op = {
  session: { user: null, operator: false, csrf: null, axes: [] },
  status: null,
  polls: 0,            // status answers received (tests wait on it)
  pollsStarted: 0,     // status requests sent
  programPoll: 0,      // pollsStarted when the program was accepted: older answers do not judge it
  program: "",         // "", "running", "finished", "stopped: ...", "refused: ..."
  jogging: {},         // axis -> keep-alive timer of a continuous jog
};
window.op = op;

const $ = (id) => document.getElementById(id);

async function post(url, body, headers) {
  const h = Object.assign({ "X-CSRF-Token": op.session.csrf || "" }, headers || {});
  if (!(body instanceof Blob)) {
    h["Content-Type"] = "application/json";
    body = JSON.stringify(body || {});
  }
  let res;
  try {
    res = await fetch(url, { method: "POST", headers: h, body: body, credentials: "same-origin" });
  } catch (e) {
    return { ok: false, error: "no answer from the page's server: " + e };
  }
  let ans;
  try { ans = await res.json(); } catch (e) { ans = { ok: false, error: "HTTP " + res.status }; }
  ans.httpStatus = res.status;
  return ans;
}

function showAnswer(ans, what) {
  const el = $("answer");
  el.className = ans.ok ? "ok" : "err";
  el.textContent = ans.ok ? what + ": ok" : what + ": " + ans.error;
}

async function cmd(name, body) {
  const ans = await post("/operator/cmd/" + name, body || {});
  showAnswer(ans, name + (body && body.axis ? " " + body.axis : ""));
  if (ans.httpStatus === 403) loadSession();      // the session ended (idle, logged out, restart)
  return ans;
}

// ------------------------------------------------------------------ session
async function loadSession() {
  const res = await fetch("/operator/session", { credentials: "same-origin" });
  op.session = await res.json();
  showSession();
}

function showSession() {
  const s = op.session;
  $("who").textContent = s.user ? "logged in as " + s.user + " (" + s.roles.join(", ") + ")" : "not logged in";
  $("readonly").textContent = s.operator ? "" : (s.logins ? "read only" : "read only: " + s.logins_off);
  $("login-form").style.display = s.user ? "none" : "inline";
  $("logout").style.display = s.user ? "inline" : "none";
  if (op.status) buildAxes(Object.keys(op.status.axes));
  for (const el of document.querySelectorAll(".cmd")) el.disabled = !s.operator;
  $("program-file").disabled = !s.operator;
}

$("login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const name = $("login-name").value;
  const pw = $("login-password");
  const ans = await post("/login", { name: name, password: pw.value });
  pw.value = "";
  $("login-error").textContent = ans.ok ? "" : ans.error;
  await loadSession();
});

$("logout").addEventListener("click", async () => {
  await post("/logout", {});
  await loadSession();
});

// ------------------------------------------------------------------ axes and jog
let builtFor = "";

function buildAxes(names) {
  const key = names.join(",") + "|" + op.session.operator;
  if (key === builtFor) return;
  builtFor = key;
  const tb = $("axes");
  tb.textContent = "";
  for (const a of names) {
    const tr = document.createElement("tr");
    tr.innerHTML =
      `<td><b>${a}</b></td><td class="pos" id="pos-${a}">-</td>` +
      `<td id="state-${a}"></td><td class="fault" id="fault-${a}"></td>` +
      `<td><button class="cmd" id="jog-minus-${a}">&minus; step</button>` +
      `<button class="cmd" id="jog-plus-${a}">+ step</button>` +
      `<button class="cmd" id="jogc-minus-${a}" title="held down: moves">&#9664; hold</button>` +
      `<button class="cmd" id="jogc-plus-${a}" title="held down: moves">hold &#9654;</button>` +
      `<button class="cmd" id="jog-stop-${a}">stop</button></td>` +
      `<td><button class="cmd" id="enable-${a}">enable</button>` +
      `<button class="cmd" id="disable-${a}">disable</button>` +
      `<button class="cmd" id="home-${a}">home</button>` +
      `<button class="cmd" id="reset-${a}">fault reset</button></td>`;
    tb.appendChild(tr);
    const step = () => parseFloat($("jog-step").value);
    $("jog-minus-" + a).onclick = () => cmd("jog", { axis: a, by: -step() });
    $("jog-plus-" + a).onclick = () => cmd("jog", { axis: a, by: step() });
    $("jog-stop-" + a).onclick = () => jogStop(a);
    $("enable-" + a).onclick = () => cmd("enable", { axis: a });
    $("disable-" + a).onclick = () => cmd("disable", { axis: a });
    $("home-" + a).onclick = () => cmd("home", { axis: a });
    $("reset-" + a).onclick = () => cmd("fault-reset", { axis: a });
    for (const [id, sign] of [["jogc-minus-" + a, -1], ["jogc-plus-" + a, 1]]) {
      const b = $(id);
      b.addEventListener("pointerdown", () => jogStart(a, sign));
      for (const ev of ["pointerup", "pointerleave", "pointercancel"]) b.addEventListener(ev, () => jogStop(a, true));
    }
  }
  for (const el of tb.querySelectorAll(".cmd")) el.disabled = !op.session.operator;
}

async function jogStart(a, sign) {
  if (op.jogging[a]) return;
  const v = sign * parseFloat($("jog-speed").value) / 1000;
  // the server stops a continuous jog it is not told to keep alive (page closed, network gone)
  op.jogging[a] = setInterval(() => post("/operator/cmd/jog-alive", { axis: a }),
                              (op.session.jog_deadman_s || 0.6) * 1000 / 3);
  const ans = await cmd("jog", { axis: a, velocity: v });
  if (!ans.ok) jogStop(a, true, true);
}

async function jogStop(a, onlyIfJogging, quiet) {
  if (onlyIfJogging && !op.jogging[a]) return;
  clearInterval(op.jogging[a]);
  delete op.jogging[a];
  if (!quiet) await cmd("jog", { axis: a, stop: true });
}

window.addEventListener("blur", () => { for (const a of Object.keys(op.jogging)) jogStop(a, true); });

// ------------------------------------------------------------------ program, MDI, feed
$("program-run").onclick = async () => {
  const f = $("program-file").files[0];
  if (!f) { showAnswer({ ok: false, error: "choose a file first" }, "program"); return; }
  op.program = "sending";
  $("program-state").textContent = "sending " + f.name + " (" + f.size + " bytes)";
  const ans = await post("/operator/program?name=" + encodeURIComponent(f.name), f,
                         { "Content-Type": "application/octet-stream" });
  op.program = ans.ok ? "running" : "refused: " + ans.error;
  op.programPoll = op.pollsStarted;
  $("program-state").textContent = ans.ok ? f.name + ": running (" + ans.lines + " lines)" : ans.error;
  $("program-state").className = ans.ok ? "" : "err";
  showAnswer(ans, "program " + f.name);
  if (ans.httpStatus === 403) loadSession();
};

for (const name of ["hold", "resume", "abort"]) $(name).onclick = () => cmd(name);
$("override").addEventListener("input", () => { $("override-value").textContent = $("override").value + " %"; });
$("override").addEventListener("change", () => cmd("override", { value: parseInt($("override").value, 10) / 100 }));
$("mdi-send").onclick = () => cmd("mdi", { line: $("mdi-line").value });
$("mdi-line").addEventListener("keydown", (ev) => { if (ev.key === "Enter") $("mdi-send").click(); });

// ------------------------------------------------------------------ the DRO
function fmt(m) { return m === null || m === undefined ? "-" : (m * 1000).toFixed(3); }

function showStatus(st, n) {
  op.status = st;
  buildAxes(Object.keys(st.axes));
  for (const [a, s] of Object.entries(st.axes)) {
    $("pos-" + a).textContent = fmt(s.y_m);
    $("state-" + a).textContent = s.state + " / " + s.phase;
    $("fault-" + a).textContent = s.fault || "";
  }
  const m = st.motion;
  if (st.error) { $("motion").textContent = st.error; return; }
  let t = m.idle ? "idle" : `line ${m.line}, ${Math.round(100 * (m.done || 0))} % done, ${(m.time_left_s || 0).toFixed(1)} s left`;
  if (m.hold) t += ", held";
  if (m.stopped_because) t += " (stopped: " + m.stopped_because + ")";
  $("motion").textContent = t + ", override " + Math.round(100 * (m.override || 0)) + " %";
  if (document.activeElement !== $("override")) {
    $("override").value = Math.round(100 * (m.override || 0));
    $("override-value").textContent = $("override").value + " %";
  }
  if (op.program === "running" && n > op.programPoll) {
    if (m.idle && !m.planning) {
      op.program = m.stopped_because ? "stopped: " + m.stopped_because : "finished";
      $("program-state").textContent = op.program;
    }
  }
}

async function poll() {
  const n = ++op.pollsStarted;
  try {
    const res = await fetch("/operator/status", { credentials: "same-origin" });
    showStatus(await res.json(), n);
    op.polls += 1;
  } catch (e) {
    $("motion").textContent = "no answer from the page's server";
  }
  setTimeout(poll, 200);
}

loadSession().then(poll);
