// ctgpp playground: the page of `ctgpp serve`. Plain JavaScript, no build step, nothing fetched
// from elsewhere: the scene and the rollout are drawn on a <canvas> from the server's JSON.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const POLL_MS = 300;
  const TRAIL_S = 3.0;        // history trail drawn behind each numbered vehicle
  const EVENT_FRESH_S = 2.0;  // an event is marked large this long, then small
  const METRIC_SKIP = new Set(["scene", "start_s", "duration_s", "history_s", "policy", "seed"]);

  const state = {
    scenes: [], options: null, sceneKey: null, scene: null,   // scene: the scene view (first frame)
    jobId: null, job: null, pollTimer: null, playback: null, playbackOf: null, firstFramePending: false,
    live: null, liveFetching: false,   // live: the streamed frames of the running job (a playback still growing)
    frame: 0, playing: false, clock: null, speed: 1,
    view: null, drag: null, staticLayer: null, staticKey: "", drivable: null,
    timings: {},
  };
  window.ctgppTimings = state.timings;   // read by the browser test and scripts/serve_first_frame.py

  // --- HTTP --------------------------------------------------------------------------------------

  async function api(path, body) {
    const init = body === undefined ? {} : {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
    };
    const response = await fetch(path, init);
    let data = null;
    try { data = await response.json(); } catch (err) { data = { message: response.statusText }; }
    if (!response.ok) {
      const error = new Error((data && data.message) || `HTTP ${response.status}`);
      error.data = data;
      throw error;
    }
    return data;
  }

  function setStatus(text, isError = false) {
    $("status").textContent = text;
    $("status").classList.toggle("error", isError);
  }

  // --- scene picker ------------------------------------------------------------------------------

  function renderSceneList() {
    const filter = $("scene-filter").value.trim().toLowerCase();
    const body = $("scene-list");
    body.replaceChildren();
    for (const s of state.scenes) {
      const text = `${s.key} ${s.map} ${s.split}`.toLowerCase();
      if (filter && !text.includes(filter)) continue;
      const row = document.createElement("tr");
      row.dataset.key = s.key;
      row.title = `${s.key} · split ${s.split} · episodes up to ${s.max_duration_s} s`;
      row.classList.toggle("selected", s.key === state.sceneKey);
      const label = s.set === "embedded" ? s.id : `${s.set}: ${s.id}`;
      for (const [value, cls] of [[label, ""], [s.map, ""], [s.duration_s.toFixed(1), "num"], [s.vehicles, "num"]]) {
        const cell = document.createElement("td");
        cell.textContent = value;
        if (cls) cell.className = cls;
        row.appendChild(cell);
      }
      row.addEventListener("click", () => selectScene(s.key));
      body.appendChild(row);
    }
  }

  async function selectScene(key) {
    const entry = state.scenes.find((s) => s.key === key);
    if (!entry) return;
    state.sceneKey = key;
    renderSceneList();
    const duration = $("duration");
    duration.max = entry.max_duration_s;
    if (Number(duration.value) > entry.max_duration_s) duration.value = entry.max_duration_s;
    setStatus(`Loading ${entry.id}…`);
    try {
      const view = await api(`/api/scenes/${encodeURIComponent(key)}?duration_s=${Number(duration.value) || 10}`);
      if (state.sceneKey !== key) return;
      state.scene = view;
      stopPlayback();
      state.playback = null;
      state.playbackOf = null;
      state.view = view.view.slice();
      await loadDrivable(view.drivable);
      state.staticKey = "";
      updatePlayer();
      draw();
      setStatus(`${view.id} (${view.map}): ${view.vehicles} vehicles at the start, ${view.history_s} s of log before it. ` +
                "Type a sentence and press Run.");
      updateRunButton();
    } catch (err) {
      setStatus(err.message, true);
    }
  }

  function loadDrivable(drivable) {
    return new Promise((resolve) => {
      const image = new Image();
      image.onload = () => { state.drivable = { image, ...drivable }; resolve(); };
      image.onerror = () => { state.drivable = null; resolve(); };
      image.src = drivable.png;
    });
  }

  // --- options and the sentence ------------------------------------------------------------------

  function renderOptions(options) {
    state.options = options;
    const policy = $("policy");
    policy.replaceChildren(...options.policies.map((name) => new Option(name, name, name === "ctgpp", name === "ctgpp")));
    $("phrasings").replaceChildren(...options.phrasings.map((p) => new Option(p)));
    $("phrasing-list").replaceChildren(...options.phrasings.map((p) => {
      const item = document.createElement("li");
      item.textContent = p;
      item.addEventListener("click", () => useSentence(p));
      return item;
    }));
    $("sentence").maxLength = options.max_sentence_chars;
    if (options.llm) {
      $("llm-option").hidden = false;
      $("llm-name").textContent = `(${options.llm.model})`;
    }
    if (!options.exports.includes("commonroad")) $("export-commonroad").disabled = true;
    updateRunButton();
  }

  function useSentence(text) {
    $("sentence").value = text;
    $("sentence").focus();
    clearRefusal();
  }

  function clearRefusal() {
    $("refusal").hidden = true;
    $("refusal-message").textContent = "";
    $("suggestions").replaceChildren();
    $("suggestions-wrap").hidden = true;
  }

  // a run may start while the last one simulates its unguided comparison: the comparison gives way
  function updateRunButton() {
    const job = state.job;
    const busy = job && (job.state === "queued" || job.state === "running");
    const comparing = busy && job.state === "running" && job.phase === "unguided";
    $("run").disabled = !(state.sceneKey && state.options) || Boolean(busy && !comparing);
    $("cancel").disabled = !busy;
  }

  // --- a run -------------------------------------------------------------------------------------

  async function run() {
    const exports = ["scenarionet", "commonroad"].filter((k) => $(`export-${k}`).checked);
    const request = {
      scene: state.sceneKey,
      sentence: $("sentence").value.trim(),
      seed: Math.max(0, Math.floor(Number($("seed").value) || 0)),
      duration_s: Number($("duration").value) || 10,
      policy: $("policy").value,
      guards: $("guards").checked,
      llm: $("llm").checked,
      compare: $("compare").checked,
      exports,
    };
    clearRefusal();
    for (const key of Object.keys(state.timings)) delete state.timings[key];
    state.firstFramePending = false;
    state.live = null;
    state.timings.run_clicked = performance.now();
    $("run").disabled = true;
    setStatus("Sending the run…");
    try {
      const job = await api("/api/runs", request);
      state.jobId = job.id;
      showJob(job);
      poll();
    } catch (err) {
      if (err.data && err.data.refused) showRefusal(err.data);
      setStatus(err.data && err.data.refused ? "The sentence was refused." : err.message, true);
      updateRunButton();
    }
  }

  // the refusal's message, and its suggestions once, under their heading only when there are some
  function showRefusal(data) {
    const suggestions = [...new Set(data.suggestions || [])];
    $("refusal").hidden = false;
    $("refusal-message").textContent = data.message;
    $("suggestions-wrap").hidden = suggestions.length === 0;
    $("suggestions").replaceChildren(...suggestions.map((s) => {
      const item = document.createElement("li");
      item.textContent = s;
      item.addEventListener("click", () => useSentence(s));
      return item;
    }));
  }

  async function cancel() {
    if (!state.jobId) return;
    try { showJob(await api(`/api/runs/${state.jobId}/cancel`, {})); } catch (err) { setStatus(err.message, true); }
  }

  function poll() {
    clearTimeout(state.pollTimer);
    state.pollTimer = setTimeout(async () => {
      const id = state.jobId;
      try {
        const job = await api(`/api/runs/${id}`);
        if (id !== state.jobId) return;
        showJob(job);
        if (job.state === "queued" || job.state === "running") poll();
      } catch (err) {
        setStatus(err.message, true);
      }
      refreshQueue();
    }, POLL_MS);
  }

  async function showJob(job) {
    state.job = job;
    updateRunButton();
    const bar = $("progress-bar");
    if (job.state === "queued") {
      bar.style.width = "0";
      setStatus(`Waiting: ${job.position === 1 ? "next in line" : `${job.position - 1} run(s) before it`}.`);
    } else if (job.state === "running") {
      const part = job.total ? job.done / job.total : 0;
      const phases = job.compare && job.sentence ? ["guided", "unguided"] : ["guided"];
      const k = Math.max(0, phases.indexOf(job.phase));
      bar.style.width = `${Math.round(100 * (job.phase.startsWith("export") ? 1 : (k + part) / phases.length))}%`;
      const what = { starting: "starting", guided: "simulating, guided by the sentence",
        unguided: "simulating the unguided run to compare" }[job.phase] || `writing the ${job.phase.replace("export ", "")} export`;
      const count = job.total ? ` — re-plan ${job.done} of ${job.total}` : "";
      setStatus(job.cancelling ? "Cancelling…" : `Running: ${what}${count}.${firstFrameNote()}`);
    } else {
      bar.style.width = job.state === "done" ? "100%" : "0";
      const total = job.seconds.total !== null ? ` in ${job.seconds.total.toFixed(1)} s` : "";
      const text = { done: `Done${total}.${firstFrameNote()}`, cancelled: job.message || "Cancelled.",
        failed: `The run failed: ${job.message}`, refused: "The sentence was refused." }[job.state];
      setStatus(text, job.state === "failed" || job.state === "refused");
      if (job.state === "refused" && $("refusal").hidden) showRefusal(job);
    }
    if (job.has_rollout && state.playbackOf !== job.id) {
      state.playbackOf = job.id;
      state.live = null;
      await loadPlayback(job.id);
    } else if (!job.has_rollout && job.frames > (state.live ? state.live.count : 0)) {
      await loadFrames(job.id);
    }
    renderResults(job);
  }

  function firstFrameNote() {
    const t = state.timings;
    return t.first_frame ? ` First frame ${((t.first_frame - t.run_clicked) / 1000).toFixed(1)} s after Run.` : "";
  }

  async function refreshQueue() {
    try {
      const runs = await api("/api/runs");
      $("queue").replaceChildren(...runs.slice(0, 20).map((r) => {
        const item = document.createElement("li");
        const st = document.createElement("span");
        st.className = "state";
        st.textContent = r.state + (r.position ? ` #${r.position}` : "");
        item.append(st, ` ${r.scene.replace("embedded:", "")} · seed ${r.seed} · ${r.sentence || "(no sentence)"}`);
        return item;
      }));
    } catch (err) { /* the queue list is a convenience */ }
  }

  // --- results -----------------------------------------------------------------------------------

  function cell(row, text, cls) {
    const td = document.createElement(row.parentElement && row.parentElement.tagName === "THEAD" ? "th" : "td");
    td.textContent = text;
    if (cls) td.className = cls;
    row.appendChild(td);
    return td;
  }

  function table(id, header, rows) {
    const t = $(id);
    t.replaceChildren();
    if (!rows.length) return t;
    const head = t.createTHead().insertRow();
    for (const h of header) { const th = document.createElement("th"); th.textContent = h; head.appendChild(th); }
    const body = t.createTBody();
    for (const r of rows) {
      const tr = body.insertRow();
      for (const c of r) {
        const td = cell(tr, c.text !== undefined ? c.text : c, c.cls);
        if (c.title) td.title = c.title;
        if (c.time !== undefined && c.time !== null) { td.style.cursor = "pointer"; td.addEventListener("click", () => seek(c.time)); }
      }
    }
    return t;
  }

  function verdictText(value) {
    if (value === true) return ["yes", "satisfied"];
    if (value === false) return ["no", "not satisfied"];
    return ["unknown", String(value)];
  }

  function fmt(value) {
    if (value === null || value === undefined) return "–";
    if (typeof value === "number") return Number.isInteger(value) ? String(value) : value.toFixed(3);
    return String(value);
  }

  function renderResults(job) {
    const record = job.record;
    const verdict = $("verdict");
    $("command").textContent = job.command;
    if (!record) {
      verdict.className = "verdict none";
      verdict.textContent = job.state === "failed" || job.state === "refused" ? "No result." : "Simulating…";
      for (const id of ["parts", "metrics", "events", "downloads"]) $(id).replaceChildren();
      $("code").textContent = "";
      $("loss-path").textContent = "";
      return;
    }
    const query = record.query;
    const base = job.baseline;
    if (query) {
      const [cls, text] = verdictText(query.satisfied);
      verdict.className = `verdict ${cls}`;
      let baseText = "";
      if (base && base.query) baseText = ` (unguided: ${verdictText(base.query.satisfied)[1]})`;
      else if (base && base.skipped) baseText = ` (${base.skipped})`;
      else if (job.compare && job.state === "running") baseText = " (unguided run in progress…)";
      verdict.textContent = `${text[0].toUpperCase()}${text.slice(1)}${baseText}`;
      const baseParts = base && base.query ? base.query.parts : [];
      table("parts", ["part of the sentence", "guided", "unguided"], query.parts.map((p, k) => {
        const b = baseParts[k];
        return [p.text,
          { text: `${p.satisfied ? "yes" : "no"} — ${p.measured}`, cls: p.satisfied ? "yes" : "no", title: p.window },
          b ? { text: `${b.satisfied ? "yes" : "no"} — ${b.measured}`, cls: b.satisfied ? "yes" : "no" } : "–"];
      }));
      $("loss-path").textContent = `from the ${query.path}${query.notes.length ? " — " + query.notes.join("; ") : ""}`;
      $("code").textContent = query.code;
    } else {
      verdict.className = "verdict none";
      verdict.textContent = "No sentence: the realism guards alone.";
      $("parts").replaceChildren();
      $("loss-path").textContent = "";
      $("code").textContent = "";
    }
    const baseMetrics = base && base.metrics ? base.metrics : null;
    const names = Object.keys(record).filter((k) => !METRIC_SKIP.has(k) && (typeof record[k] === "number" || record[k] === null));
    table("metrics", ["metric", "guided", "unguided"], names.map((k) => [k, fmt(record[k]),
      baseMetrics ? fmt(baseMetrics[k]) : (job.compare && job.sentence && job.state === "running" ? "…" : "–")]));
    const rows = [];
    for (const e of record.events) {
      const when = (x) => (x ? `${x.time_s.toFixed(1)} s` : "");
      const hit = e.collision ? `${e.collision.time_s.toFixed(1)} s with ${e.collision.vehicle !== null ? "vehicle " + e.collision.vehicle : "a replayed " + e.collision.kind} (${e.collision.partner})` : "";
      if (!hit && !e.offroad && !e.lane_leave && !e.stop && !e.beyond_map) continue;
      rows.push([String(e.vehicle), { text: hit, time: e.collision && e.collision.time_s },
        { text: when(e.offroad), time: e.offroad && e.offroad.time_s },
        { text: when(e.lane_leave), time: e.lane_leave && e.lane_leave.time_s },
        { text: when(e.stop), time: e.stop && e.stop.time_s },
        { text: e.beyond_map ? `${when(e.beyond_map)} (${e.beyond_map.reason})` : "" }]);
    }
    table("events", ["veh.", "collision", "off-road", "lane leave", "stop", "off the map"], rows);
    if (!rows.length) $("events").textContent = `No events: ${record.events.length} vehicles without collision, off-road, lane leave or stop.`;
    $("downloads").replaceChildren(...job.files.filter((f) => f !== "request.json").map((name) => {
      const item = document.createElement("li");
      const link = document.createElement("a");
      link.href = `/api/runs/${job.id}/files/${encodeURIComponent(name)}`;
      link.textContent = name;
      link.download = name;
      item.appendChild(link);
      return item;
    }));
  }

  // --- playback ----------------------------------------------------------------------------------

  async function loadPlayback(id) {
    try {
      const data = await api(`/api/runs/${id}/playback`);
      if (id !== state.jobId) return;
      state.playback = data;
      state.firstFramePending = state.timings.first_frame === undefined;
      state.frame = data.current;
      updatePlayer();
      play();
    } catch (err) {
      setStatus(err.message, true);
    }
  }

  // the frames streamed so far (each re-plan's executed steps), drawn at the newest one
  async function loadFrames(id) {
    if (state.liveFetching) return;
    state.liveFetching = true;
    try {
      const since = state.live && state.live.jobId === id ? state.live.count : 0;
      const data = await api(`/api/runs/${id}/frames?since=${since}`);
      if (id !== state.jobId || state.playbackOf === id || !data.header || !data.frames.length) return;
      if (data.start === 0 || !state.live) state.live = startLive(id, data.header);
      appendFrames(state.live, data.start, data.frames);
      stopPlayback();
      state.playback = state.live.playback;
      state.frame = state.live.playback.time_s.length - 1;
      if (state.timings.first_frame === undefined) state.firstFramePending = true;
      updatePlayer();
      draw();
    } catch (err) {
      setStatus(err.message, true);
    } finally {
      state.liveFetching = false;
    }
  }

  function startLive(id, header) {
    const agents = header.agents.map((a) => ({ ...a, x: [], y: [], yaw: [], speed: [] }));
    return { jobId: id, count: 0, playback: { scene: state.scene ? state.scene.id : "", dt_s: header.dt_s,
      current: header.current, time_s: [], agents, events: [], named: [], live: true } };
  }

  function appendFrames(live, start, frames) {
    const p = live.playback;
    frames.forEach((frame, i) => {
      const k = start + i;
      p.time_s[k] = Math.round((k - p.current) * p.dt_s * 1000) / 1000;
      frame.forEach((s, j) => {
        const a = p.agents[j];
        [a.x[k], a.y[k], a.yaw[k], a.speed[k]] = s === null ? [null, null, null, null] : s;
      });
    });
    live.count = p.time_s.length;
  }

  function updatePlayer() {
    const p = state.playback;
    const scrub = $("scrub");
    scrub.disabled = !p;
    $("play").disabled = !p;
    if (!p) { $("time-label").textContent = "t = 0.0 s"; $("canvas").dataset.frame = "-1"; return; }
    scrub.max = p.time_s.length - 1;
    scrub.value = state.frame;
  }

  function play() {
    const p = state.playback;
    if (!p) return;
    if (state.frame >= p.time_s.length - 1) {  // at the end: back to the start, shown at once
      state.frame = p.current;
      draw();
    }
    state.playing = true;
    state.clock = { start: performance.now(), frame: state.frame };
    $("play").textContent = "Pause";
    requestAnimationFrame(tick);
  }

  function stopPlayback() {
    state.playing = false;
    $("play").textContent = "Play";
  }

  function tick(now) {
    const p = state.playback;
    if (!state.playing || !p) return;
    const steps = Math.floor(((now - state.clock.start) / 1000) * state.speed / p.dt_s);
    state.frame = Math.min(p.time_s.length - 1, state.clock.frame + steps);
    draw();
    if (state.frame >= p.time_s.length - 1) { stopPlayback(); return; }
    requestAnimationFrame(tick);
  }

  function seek(time) {
    const p = state.playback;
    if (!p) return;
    stopPlayback();
    state.frame = Math.max(0, Math.min(p.time_s.length - 1, p.current + Math.round(time / p.dt_s)));
    draw();
  }

  // --- drawing -----------------------------------------------------------------------------------

  function resizeCanvas() {
    const canvas = $("canvas");
    const width = Math.max(300, Math.round(canvas.clientWidth * (window.devicePixelRatio || 1)));
    const height = Math.round(width * 0.72);
    if (canvas.width !== width || canvas.height !== height) {
      canvas.width = width;
      canvas.height = height;
      state.staticKey = "";
    }
  }

  function transform() {
    const canvas = $("canvas");
    const [x0, y0, x1, y1] = state.view;
    const scale = Math.min(canvas.width / (x1 - x0), canvas.height / (y1 - y0));
    const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
    return { scale, x: (wx) => canvas.width / 2 + (wx - cx) * scale, y: (wy) => canvas.height / 2 - (wy - cy) * scale,
      inv: (px, py) => [cx + (px - canvas.width / 2) / scale, cy - (py - canvas.height / 2) / scale],
      matrix: [scale, 0, 0, -scale, canvas.width / 2 - cx * scale, canvas.height / 2 + cy * scale] };
  }

  function staticLayer(tf) {
    const canvas = $("canvas");
    const key = `${state.scene && state.scene.id}|${state.view.join(",")}|${canvas.width}x${canvas.height}`;
    if (state.staticKey === key && state.staticLayer) return state.staticLayer;
    const layer = state.staticLayer || document.createElement("canvas");
    layer.width = canvas.width;
    layer.height = canvas.height;
    const ctx = layer.getContext("2d");
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#f7f7f5";
    ctx.fillRect(0, 0, layer.width, layer.height);
    const d = state.drivable;
    if (d) {  // row 0 of the raster is its southern edge: drawn in world coordinates, y up
      ctx.setTransform(...tf.matrix);
      ctx.imageSmoothingEnabled = false;
      ctx.drawImage(d.image, d.x0, d.y0, d.width * d.resolution_m, d.height * d.resolution_m);
      ctx.setTransform(1, 0, 0, 1, 0, 0);
    }
    ctx.strokeStyle = "rgba(120, 130, 150, 0.55)";
    ctx.lineWidth = 1;
    ctx.setLineDash([6, 5]);
    for (const lane of state.scene ? state.scene.lanes : []) {
      ctx.beginPath();
      for (let k = 0; k < lane.length; k += 2) {
        const x = tf.x(lane[k]), y = tf.y(lane[k + 1]);
        if (k === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
      }
      ctx.stroke();
    }
    ctx.setLineDash([]);
    state.staticLayer = layer;
    state.staticKey = key;
    return layer;
  }

  // the agents of the current frame: {number, type, color, x, y, yaw, length, width, speed, moving}
  function agentsNow() {
    const p = state.playback;
    if (!p) return state.scene ? state.scene.agents : [];
    const k = state.frame;
    const out = [];
    for (const a of p.agents) {
      if (a.x[k] === null) continue;
      out.push({ number: a.number, type: a.type, color: a.color, length: a.length, width: a.width,
        x: a.x[k], y: a.y[k], yaw: a.yaw[k], speed: a.speed[k], moving: a.moving, track: a });
    }
    return out;
  }

  function corners(a) {
    const c = Math.cos(a.yaw), s = Math.sin(a.yaw), l = a.length / 2, w = a.width / 2;
    return [[l, w], [l, -w], [-l, -w], [-l, w]].map(([u, v]) => [a.x + u * c - v * s, a.y + u * s + v * c]);
  }

  function draw() {
    if (!state.scene) return;
    resizeCanvas();
    const canvas = $("canvas");
    const ctx = canvas.getContext("2d");
    const tf = transform();
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.drawImage(staticLayer(tf), 0, 0);
    const p = state.playback;
    const named = new Set(p ? p.named : []);
    const agents = agentsNow();
    if (p) drawPaths(ctx, tf, p);
    // replayed agents first, numbered vehicles above them
    agents.sort((a, b) => (a.number >= 0) - (b.number >= 0));
    for (const a of agents) {
      const pts = corners(a).map(([x, y]) => [tf.x(x), tf.y(y)]);
      ctx.beginPath();
      pts.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
      ctx.closePath();
      ctx.fillStyle = a.color;
      ctx.globalAlpha = a.number >= 0 ? 0.95 : 0.7;
      ctx.fill();
      ctx.globalAlpha = 1;
      ctx.lineWidth = named.has(a.number) ? 3 : 1;
      ctx.strokeStyle = "#111";
      ctx.stroke();
      if (a.number >= 0) {  // the front edge
        ctx.beginPath();
        ctx.moveTo(...pts[0]);
        ctx.lineTo(...pts[1]);
        ctx.lineWidth = 2;
        ctx.stroke();
      }
    }
    if (p) drawEvents(ctx, tf, p);
    for (const a of agents) if (a.number >= 0) drawTag(ctx, tf, a, named.has(a.number));
    const label = p ? `t = ${p.time_s[state.frame].toFixed(1)} s` : "t = 0.0 s";
    $("time-label").textContent = label;
    if (p) { $("scrub").value = state.frame; canvas.dataset.frame = String(state.frame); }
    ctx.font = `${Math.round(13 * (window.devicePixelRatio || 1))}px system-ui, sans-serif`;
    ctx.fillStyle = "rgba(20, 24, 36, 0.8)";
    ctx.fillText(`${state.scene.id}   ${label}${p && state.frame < p.current ? " (logged history)" : ""}`, 10, 20);
    if (p && state.firstFramePending && state.frame > p.current) {  // a simulated frame of the run is on the canvas
      state.firstFramePending = false;
      state.timings.first_frame = performance.now();
      state.timings.seconds = (state.timings.first_frame - state.timings.run_clicked) / 1000;
      if (state.job) showJob(state.job);
    }
  }

  function drawPaths(ctx, tf, p) {
    const k = state.frame;
    const trail = Math.round(TRAIL_S / p.dt_s);
    for (const a of p.agents) {
      if (a.number < 0 || !a.moving) continue;
      ctx.strokeStyle = a.color;
      // the whole simulated future, faint; the last 3 s behind the vehicle, stronger
      for (const [from, to, alpha, width] of [[p.current, a.x.length - 1, 0.18, 2], [Math.max(0, k - trail), k, 0.5, 3]]) {
        ctx.beginPath();
        let started = false;
        for (let i = from; i <= to; i++) {
          if (a.x[i] === null) { started = false; continue; }
          const x = tf.x(a.x[i]), y = tf.y(a.y[i]);
          if (started) ctx.lineTo(x, y); else { ctx.moveTo(x, y); started = true; }
        }
        ctx.globalAlpha = alpha;
        ctx.lineWidth = width;
        ctx.stroke();
      }
    }
    ctx.globalAlpha = 1;
  }

  function drawEvents(ctx, tf, p) {
    const t = p.time_s[state.frame];
    for (const e of p.events) {
      if (e.time_s > t + 1e-6) continue;
      const fresh = t - e.time_s < EVENT_FRESH_S;
      const size = (fresh ? 16 : 9) * (window.devicePixelRatio || 1);
      const x = tf.x(e.x), y = tf.y(e.y);
      ctx.beginPath();
      if (e.kind === "collision") {
        for (let i = 0; i < 10; i++) {
          const r = i % 2 ? size * 0.42 : size, angle = -Math.PI / 2 + (i * Math.PI) / 5;
          ctx.lineTo(x + r * Math.cos(angle), y + r * Math.sin(angle));
        }
        ctx.fillStyle = "#ffd700";
      } else {
        ctx.moveTo(x, y - size);
        ctx.lineTo(x + size * 0.87, y + size * 0.5);
        ctx.lineTo(x - size * 0.87, y + size * 0.5);
        ctx.fillStyle = "#ff00ff";
      }
      ctx.closePath();
      ctx.globalAlpha = fresh ? 0.85 : 0.45;
      ctx.fill();
      ctx.globalAlpha = 1;
      ctx.lineWidth = 1.2;
      ctx.strokeStyle = "#111";
      ctx.stroke();
    }
  }

  function drawTag(ctx, tf, a, isNamed) {
    const ratio = window.devicePixelRatio || 1;
    const text = String(a.number);
    ctx.font = `bold ${Math.round(11 * ratio)}px system-ui, sans-serif`;
    const w = ctx.measureText(text).width + 6 * ratio, h = 14 * ratio;
    const x = tf.x(a.x) - w / 2, y = tf.y(a.y) - h - Math.max(a.length, a.width) * tf.scale * 0.5 - 2 * ratio;
    ctx.fillStyle = a.color;
    ctx.fillRect(x, y, w, h);
    ctx.lineWidth = isNamed ? 2.5 : 1;
    ctx.strokeStyle = "#111";
    ctx.strokeRect(x, y, w, h);
    ctx.fillStyle = textColor(a.color);
    ctx.textBaseline = "middle";
    ctx.fillText(text, x + 3 * ratio, y + h / 2 + 0.5);
    ctx.textBaseline = "alphabetic";
  }

  function textColor(hex) {
    const [r, g, b] = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
    return 0.2126 * r + 0.7152 * g + 0.0722 * b > 0.5 ? "#000" : "#fff";
  }

  // --- hover, zoom and pan -----------------------------------------------------------------------

  function canvasPoint(event) {
    const canvas = $("canvas");
    const box = canvas.getBoundingClientRect();
    return [(event.clientX - box.left) * (canvas.width / box.width), (event.clientY - box.top) * (canvas.height / box.height)];
  }

  function agentAt(wx, wy, tolerance) {
    let best = null;
    for (const a of agentsNow()) {
      const c = Math.cos(a.yaw), s = Math.sin(a.yaw), dx = wx - a.x, dy = wy - a.y;
      const u = dx * c + dy * s, v = -dx * s + dy * c;
      if (Math.abs(u) <= a.length / 2 + tolerance && Math.abs(v) <= a.width / 2 + tolerance) {
        if (!best || (a.number >= 0 && best.number < 0)) best = a;
      }
    }
    return best;
  }

  function describe(a) {
    const speed = `${(a.speed || 0).toFixed(1)} m/s`;
    if (a.number < 0) return `replayed ${a.type} · ${speed}`;
    const moving = a.moving ? "moving at the start" : "stationary at the start (held still)";
    return `vehicle ${a.number} · ${a.type} · ${speed} · ${moving}`;
  }

  function onMove(event) {
    if (!state.scene) return;
    const [px, py] = canvasPoint(event);
    const tf = transform();
    if (state.drag) {
      const dx = (px - state.drag.px) / tf.scale, dy = (py - state.drag.py) / tf.scale;
      state.view = [state.drag.view[0] - dx, state.drag.view[1] + dy, state.drag.view[2] - dx, state.drag.view[3] + dy];
      draw();
      return;
    }
    const [wx, wy] = tf.inv(px, py);
    $("cursor").textContent = `x ${wx.toFixed(1)}, y ${wy.toFixed(1)} m`;
    const a = agentAt(wx, wy, 4 / tf.scale);
    const tip = $("tooltip");
    if (!a) { tip.hidden = true; return; }
    const box = $("canvas").getBoundingClientRect();
    tip.textContent = describe(a);
    tip.hidden = false;
    tip.style.left = `${event.clientX - box.left + 14}px`;
    tip.style.top = `${event.clientY - box.top + 10}px`;
  }

  function onWheel(event) {
    if (!state.scene) return;
    event.preventDefault();
    const tf = transform();
    const [wx, wy] = tf.inv(...canvasPoint(event));
    const f = event.deltaY > 0 ? 1.15 : 1 / 1.15;
    const [x0, y0, x1, y1] = state.view;
    state.view = [wx + (x0 - wx) * f, wy + (y0 - wy) * f, wx + (x1 - wx) * f, wy + (y1 - wy) * f];
    draw();
  }

  // where vehicle `number` is drawn now, in CSS pixels from the canvas's top left (for tests)

  window.ctgppVehicleAt = (number) => {
    const a = agentsNow().find((agent) => agent.number === number);
    if (!a || !state.view) return null;
    const tf = transform(), canvas = $("canvas"), ratio = canvas.clientWidth / canvas.width;
    return { x: tf.x(a.x) * ratio, y: tf.y(a.y) * ratio };
  };

  // --- start -------------------------------------------------------------------------------------

  async function start() {
    const canvas = $("canvas");
    canvas.addEventListener("mousemove", onMove);
    canvas.addEventListener("mouseleave", () => { $("tooltip").hidden = true; state.drag = null; });
    canvas.addEventListener("mousedown", (e) => { const [px, py] = canvasPoint(e); state.drag = { px, py, view: state.view.slice() }; });
    window.addEventListener("mouseup", () => { state.drag = null; });
    canvas.addEventListener("wheel", onWheel, { passive: false });
    canvas.addEventListener("dblclick", () => { if (state.scene) { state.view = state.scene.view.slice(); draw(); } });
    window.addEventListener("resize", draw);
    $("scene-filter").addEventListener("input", renderSceneList);
    $("run").addEventListener("click", run);
    $("cancel").addEventListener("click", cancel);
    $("sentence").addEventListener("keydown", (e) => { if (e.key === "Enter" && !$("run").disabled) run(); });
    $("sentence").addEventListener("input", clearRefusal);   // a refusal is of the sentence it was given
    $("play").addEventListener("click", () => (state.playing ? stopPlayback() : play()));
    $("scrub").addEventListener("input", () => { stopPlayback(); state.frame = Number($("scrub").value); draw(); });
    $("speed").addEventListener("change", () => { state.speed = Number($("speed").value); if (state.playing) play(); });
    $("duration").addEventListener("change", () => { if (state.sceneKey && !state.playback) selectScene(state.sceneKey); });
    try {
      state.scenes = await api("/api/scenes");
      renderSceneList();
      setStatus("Pick a scene.");
      refreshQueue();
      renderOptions(await api("/api/options"));
    } catch (err) {
      setStatus(err.message, true);
    }
  }

  start();
})();
