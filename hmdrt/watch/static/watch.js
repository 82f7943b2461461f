// hmdrt watch: the page. Plain JS, no build step; uPlot (vendored) draws the plots.
// window.hmdrtWatch holds what the page has received, for people and tests to look at.
"use strict";
(() => {
  const WINDOW_S = 20; // seconds of frames the plots keep
  const MAX_CANVAS = 960; // the preview is drawn this wide at most (whole multiples of its size)
  const MARKER = "rgb(0, 255, 0)"; // gaze point
  const FOVEA = "rgb(255, 200, 0)";
  const REPEAT = "rgb(241, 194, 27)"; // a repeat's marker on the frame-time plot
  const COLOURS = ["#4ea1ff", "#ff8389", "#6fdc8c", "#f1c21b", "#be95ff", "#3ddbd9", "#ff7eb6"];
  const $ = (id) => document.getElementById(id);
  const state = (window.hmdrtWatch = {
    hello: null, status: null, report: null, previews: 0, lastPreview: null, frames: 0, replies: [], charts: {},
  });

  // the token: taken from the URL once, then kept in this tab's session storage and out of the address bar
  const query = new URLSearchParams(location.search);
  if (query.has("token")) {
    sessionStorage.setItem("hmdrt-watch-token", query.get("token"));
    history.replaceState(null, "", location.pathname);
  }
  let token = sessionStorage.getItem("hmdrt-watch-token") || "";

  // --- plots ----------------------------------------------------------------------------------------------------
  // per-VSync series, in step with t; a VSync's gaze error comes with a later VSync's point and is put at its own;
  // a repeat (a VSync that showed the previous frame again) is a marker on the period line
  const SERIES = [
    "t", "vsync", "frame", "period", "repeat", "misses", "repeats", "gaze", "pose", "errorLeft", "errorRight", "fovea",
    "level",
  ];
  const data = { ...Object.fromEntries(SERIES.map((key) => [key, []])), knobs: {} };
  let t0 = null, lastVsync = -1, knobNames = [], recent = [];

  // with the cursor off a chart, its legend gives each series' newest value (uPlot's would read "--")
  function legendLatest(u) {
    if (u.cursor.left >= 0) return;
    u.setLegend({ idxs: u.data.map((values) => {
      let i = values.length - 1;
      while (i >= 0 && values[i] == null) i--;
      return i < 0 ? null : i;
    }) });
  }

  function chart(id, title, series, scales, axes) {
    const el = $(id);
    const grid = { stroke: "#30363d", width: 1 };
    const opts = {
      title, width: Math.max(el.clientWidth, 400), height: 170,
      hooks: { draw: [legendLatest], setCursor: [legendLatest] },
      scales: { x: { time: false }, ...scales },
      series: [{ label: "s" }, ...series.map((s, i) => ({ stroke: COLOURS[i % COLOURS.length], width: 1.5, ...s }))],
      axes: [{ stroke: "#b8c0c8", grid }, ...axes.map((a) => ({ stroke: "#b8c0c8", grid, ...a }))],
    };
    if (state.charts[id]) state.charts[id].destroy();
    state.charts[id] = new uPlot(opts, [[], ...series.map(() => [])], el);
    return state.charts[id];
  }

  function makeCharts() {
    chart("plot-frame", "frame time (ms) against the period; repeats marked on it", [
      { label: "frame ms", spanGaps: true }, // drawn across the repeats between new frames
      { label: "period ms", dash: [4, 4] },
      { label: "repeat", stroke: REPEAT, paths: () => null, points: { show: true, size: 7, fill: REPEAT },
        value: (u, v, si, i) => (v == null ? "–" : `at ${u.data[0][i].toFixed(1)} s`) },
    ], {}, [{}]);
    chart("plot-misses", "misses and repeats in the last second", [{ label: "misses" }, { label: "repeats" }], {}, [{}]);
    chart("plot-latency", "latency (ms)", [{ label: "gaze-to-photon" }, { label: "pose-to-photon" }], {}, [{}]);
    chart("plot-gaze-error", "gaze error at photon time (deg) against the foveal radius",
      [{ label: "left eye" }, { label: "right eye" }, { label: "foveal radius", dash: [4, 4] }], {}, [{}]);
    controllerChart();
  }

  function controllerChart() {
    chart(
      "plot-controller",
      "controller level and knobs",
      [{ label: "level", scale: "level" }, ...knobNames.map((name) => ({ label: name, scale: "knob" }))],
      { level: { range: [0, 1] }, knob: {} },
      [{ scale: "level" }, { scale: "knob", side: 1, grid: { show: false } }],
    );
  }

  function plot() {
    const t = data.t;
    state.charts["plot-frame"].setData([t, data.frame, data.period, data.repeat]);
    state.charts["plot-misses"].setData([t, data.misses, data.repeats]);
    state.charts["plot-latency"].setData([t, data.gaze, data.pose]);
    state.charts["plot-gaze-error"].setData([t, data.errorLeft, data.errorRight, data.fovea]);
    state.charts["plot-controller"].setData([t, data.level, ...knobNames.map((n) => data.knobs[n] || t.map(() => null))]);
  }

  function addPoints(points) {
    const hz = state.status && state.status.status && state.status.status.vsync_hz;
    const perSecond = Math.max(1, Math.round(hz || 30));
    for (const p of points) {
      if (typeof p.t_ns !== "number") continue;
      if (t0 === null || p.vsync < lastVsync) { // a new run: start the plots afresh
        t0 = p.t_ns;
        for (const key of SERIES) data[key] = [];
        data.knobs = {};
        recent = [];
      }
      lastVsync = p.vsync;
      recent.push(p);
      if (recent.length > perSecond) recent.shift();
      data.t.push((p.t_ns - t0) / 1e9);
      data.vsync.push(p.vsync);
      data.frame.push(p.frame_ms);
      data.period.push(hz ? 1000 / hz : null);
      data.repeat.push(p.shown === "repeat" && hz ? 1000 / hz : null);
      data.misses.push(recent.filter((r) => r.missed).length);
      data.repeats.push(recent.filter((r) => r.shown === "repeat").length);
      data.gaze.push(p.gaze_ms);
      data.pose.push(p.pose_ms);
      for (const key of ["errorLeft", "errorRight", "fovea"]) data[key].push(null);
      for (const e of p.gaze_errors || []) {
        const at = data.vsync.lastIndexOf(e.vsync);
        if (at < 0) continue; // before the plots' window
        data.errorLeft[at] = e.left_deg;
        data.errorRight[at] = e.right_deg;
        data.fovea[at] = e.fovea_deg;
      }
      data.level.push(p.level ?? null);
      for (const name of knobNames) {
        (data.knobs[name] ||= data.t.slice(0, -1).map(() => null)).push(p.params ? p.params[name] ?? null : null);
      }
    }
    const from = data.t.findIndex((t) => t >= data.t[data.t.length - 1] - WINDOW_S);
    if (from > 0) {
      for (const key of SERIES) data[key].splice(0, from);
      for (const name of knobNames) if (data.knobs[name]) data.knobs[name].splice(0, from);
    }
    state.frames += points.length;
    plot();
  }

  // --- preview --------------------------------------------------------------------------------------------------
  const canvas = $("preview");
  const ctx = canvas.getContext("2d");
  let previews = Promise.resolve();

  async function showPreview(buffer) {
    const length = new DataView(buffer).getUint32(0);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, length)));
    const bitmap = await createImageBitmap(new Blob([new Uint8Array(buffer, 4 + length)], { type: "image/jpeg" }));
    const k = Math.max(1, Math.floor(MAX_CANVAS / header.width));
    if (canvas.width !== header.width * k || canvas.height !== header.height * k) {
      canvas.width = header.width * k;
      canvas.height = header.height * k;
    }
    ctx.drawImage(bitmap, 0, 0, canvas.width, canvas.height);
    bitmap.close();
    for (const eye of header.eyes) {
      ctx.save();
      ctx.beginPath();
      ctx.rect(eye.x0 * k, 0, eye.width * k, canvas.height); // each eye's marks stay on its own half
      ctx.clip();
      const [gx, gy] = eye.gaze.map((v) => v * k);
      if (eye.fovea) {
        ctx.setLineDash([6, 4]);
        ctx.strokeStyle = FOVEA;
        ctx.lineWidth = 2;
        ctx.beginPath();
        ctx.ellipse(gx, gy, eye.fovea[0] * k, eye.fovea[1] * k, 0, 0, 2 * Math.PI);
        ctx.stroke();
        ctx.setLineDash([]);
      }
      ctx.strokeStyle = ctx.fillStyle = MARKER;
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(gx, gy, Math.max(4, 2 * k), 0, 2 * Math.PI);
      header.gaze_known ? ctx.fill() : ctx.stroke();
      ctx.beginPath();
      ctx.moveTo(gx - 6 * k, gy); ctx.lineTo(gx + 6 * k, gy);
      ctx.moveTo(gx, gy - 6 * k); ctx.lineTo(gx, gy + 6 * k);
      ctx.stroke();
      ctx.restore();
    }
    const fovea = header.fovea_deg == null ? "no foveal region" : `fovea ${header.fovea_deg.toFixed(1)} deg`;
    $("preview-info").textContent = `VSync ${header.vsync} (${header.shown}), ${header.method}, ${fovea}` +
      (header.gaze_known ? "" : ", no gaze sample: rendered straight ahead");
    state.lastPreview = header;
    state.previews += 1;
  }

  // --- status, tables, controls ---------------------------------------------------------------------------------
  let specEdited = false;
  const fmt = (v, digits = 1) => (v == null ? "–" : typeof v === "number" ? (Number.isInteger(v) ? String(v) : v.toFixed(digits)) : String(v));

  function fillTable(tbody, rows) {
    tbody.replaceChildren(...rows.map((cells) => {
      const tr = document.createElement("tr");
      for (const cell of cells) {
        const td = document.createElement("td");
        td.textContent = cell;
        tr.append(td);
      }
      return tr;
    }));
  }

  function onStatus(message) {
    state.status = message;
    const s = message.status || {};
    $("connection").textContent = message.connected ? "connected" : `no compositor: ${message.control_why || s.error || ""}`;
    $("connection").className = message.connected ? "good" : "bad";
    if (message.connected) {
      const shown = s.shown || {};
      $("run").textContent = `${s.method} on ${s.scene} at ${s.profile} (${s.vsync_hz} Hz): ${shown.new} on time, ` +
        `${shown.late} late, ${shown.repeat} repeated`;
      if (!specEdited && document.activeElement !== $("spec")) {
        $("spec").value = s.method;
        $("method").value = s.method.split("?")[0];
      }
    }
    fillTable($("drivers").tBodies[0], Object.entries(message.drivers || {}).map(([device, d]) => [
      device, fmt(d.state), fmt(d.gaze_hz), fmt(d.pose_hz), fmt(d.samples), fmt(d.dropped), fmt(d.invalid),
      fmt(d.malformed), fmt(d.reconnects), fmt(d.offset_ms, 3), fmt(d.drift_ppm, 2),
    ]));
    const security = s.security || {};
    const watch = message.watch || {};
    const refused = watch.refused || {};
    const timedOut = watch.timed_out || {};
    fillTable($("security").tBodies[0], [
      ["compositor access", security.curve ? "CURVE"
        : String((s.endpoints || {}).control).startsWith("ipc://") ? "this user (ipc://)" : "loopback (tcp://)"],
      ...(security.curve ? [["handshakes admitted", fmt(security.admitted)], ["handshakes refused", fmt(security.refused)]] : []),
      ["control commands refused", fmt(security.commands_refused)],
      ["snapshots refused", fmt(security.snapshots_refused)],
      ["watch: refused (host / origin / token / message)",
        `${fmt(refused.host)} / ${fmt(refused.origin)} / ${fmt(refused.token)} / ${fmt(refused.message)}`],
      ["watch: bad HTTP requests (answered 400)", fmt(refused.bad_http)],
      ["watch: connections / pages open", `${fmt(watch.connections)} / ${fmt(watch.pages)}`],
      ["watch: refused over the cap (connections / pages)", `${fmt(refused.connections)} / ${fmt(refused.pages)}`],
      ["watch: timed out (request / idle)", `${fmt(timedOut.request)} / ${fmt(timedOut.idle)}`],
    ]);
    updateControls();
  }

  function onStats(report) {
    state.report = report;
    const c = report.controller;
    const names = c && c.trajectory && c.trajectory.length ? Object.keys(c.trajectory[c.trajectory.length - 1].knobs || {}) : [];
    if (names.join() !== knobNames.join()) {
      knobNames = names;
      data.knobs = {};
      controllerChart();
    }
    const frame = report.frame_ms || {};
    const error = report.gaze_error_at_photon_deg || {};
    const eyes = ["left", "right"].filter((eye) => error[eye]);
    const beyond = eyes.map((eye) => error[eye].beyond_fovea).filter((share) => share != null);
    $("summary").textContent = `${fmt(report.achieved_hz)} Hz achieved, miss rate ${fmt(100 * (report.miss_rate || 0), 2)}%, ` +
      `frame p99 ${fmt(frame.p99)} ms, gaze error p95 ${eyes.map((eye) => fmt(error[eye].p95, 2)).join(" / ") || "–"} deg` +
      (beyond.length ? ` (${fmt(100 * Math.max(...beyond), 1)}% beyond the fovea)` : "");
  }

  function updateControls() {
    const privileged = state.hello && state.hello.privileged;
    const allowed = state.status && state.status.control_allows;
    const open = ws && ws.readyState === WebSocket.OPEN;
    for (const id of ["method", "spec", "apply", "snapshot", "shutdown"]) $(id).disabled = !(privileged && allowed && open);
    $("controls-why").textContent = !privileged
      ? "read-only: open the address hmdrt watch printed (the one with ?token=) to change the compositor"
      : !allowed ? `read-only: ${(state.status && state.status.control_why) || "no compositor"}` : "";
  }

  function onHello(hello) {
    state.hello = hello;
    const select = $("method");
    select.replaceChildren(...Object.keys(hello.methods).map((name) => new Option(name, name)));
    updateControls();
  }

  function onReply(reply) {
    state.replies.push(reply);
    $("reply").textContent = reply.ok ? `done: ${JSON.stringify(reply)}` : `refused: ${reply.error}`;
    $("reply").className = reply.ok ? "good" : "bad";
    specEdited = false;
  }

  function onLog(record) {
    const li = document.createElement("li");
    li.textContent = `${record.level}: ${record.logger}: ${record.message}`;
    li.className = record.level === "error" ? "bad" : record.level === "warning" ? "warning" : "";
    const log = $("log");
    log.append(li);
    while (log.children.length > 50) log.firstChild.remove();
  }

  // --- the websocket --------------------------------------------------------------------------------------------
  let ws = null;
  let nextId = 1;

  function send(command) {
    command.id = nextId++;
    ws.send(JSON.stringify(command));
    $("reply").textContent = `${command.cmd}...`;
    $("reply").className = "";
  }

  function connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    ws = new WebSocket(`${scheme}://${location.host}/ws` + (token ? `?token=${encodeURIComponent(token)}` : ""));
    ws.binaryType = "arraybuffer";
    let opened = false;
    ws.onopen = () => { opened = true; updateControls(); };
    ws.onmessage = (event) => {
      if (typeof event.data !== "string") {
        previews = previews.then(() => showPreview(event.data)).catch((error) => console.warn("preview:", error));
        return;
      }
      const message = JSON.parse(event.data);
      ({ hello: onHello, status: onStatus, stats: (m) => onStats(m.report), frames: (m) => addPoints(m.frames),
        log: (m) => onLog(m.record), reply: onReply })[message.type]?.(message);
    };
    ws.onclose = () => {
      if (!opened && token) { // refused: a token of another run; go on read-only
        token = "";
        sessionStorage.removeItem("hmdrt-watch-token");
      }
      $("connection").textContent = "disconnected from hmdrt watch; retrying";
      $("connection").className = "bad";
      updateControls();
      setTimeout(connect, 1000);
    };
  }

  $("spec").addEventListener("input", () => { specEdited = true; });
  $("method").addEventListener("change", () => { $("spec").value = $("method").value; specEdited = true; });
  $("controls").addEventListener("submit", (event) => {
    event.preventDefault();
    send({ cmd: "set", method: $("spec").value.trim() });
  });
  $("snapshot").addEventListener("click", () => send({ cmd: "snapshot" }));
  $("shutdown").addEventListener("click", () => {
    if (confirm("Shut the compositor down? Its run ends and its report is written.")) send({ cmd: "shutdown" });
  });
  makeCharts();
  updateControls();
  connect();
})();
