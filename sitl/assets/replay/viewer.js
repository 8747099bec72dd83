// The race replay viewer (sitl/src/replay.rs writes it into every replay page).
// World frame: ENU metres, z up, as the simulator's. Drones are drawn at 0.5 m across
// (about five times a Crazyflie) so that they can be seen at track scale.
//
// URL options after '#', '&'-separated: episode=N, t=SECONDS (or t=overtake: the first
// sustained overtake, else the first overtake; offset=SECONDS moves it), view=chase|orbit|top,
// speed=X, play=1,
// probe=1 (the 3-D view alone, from above, for pixel checks: see FRAMING below).
'use strict';
// One block, not a function: its names stay out of the page's global scope.
{

  const COLORS = {
    background: '#14171c', grid: '#262b33', centerline: '#5a6472', gate: '#f2f2f2',
    ego: '#ff5a1f', opponent: '#2f8cff', egoTrail: '#ffb08f', opponentTrail: '#9cc8ff',
    rotor: '#3a3f48', nose: '#ffffff', crash: '#ff3b5c', gold: '#ffc53d',
  };
  const DRONES = [{ key: 'ego', name: 'ego' }, { key: 'opponent', name: 'opponent' }];
  const STATE_FLOATS = 8; // x, y, z, qw, qx, qy, qz, speed per step (replay.rs)
  // Value j of step k of one drone's states.
  const stateAt = (s, k, j) => s[k * STATE_FLOATS + j];
  const TRAIL_S = 1.5;
  const GATE_BAR_M = 0.1;
  // Where the parts the CI's probes look for sit in the drone's body frame (x forward, y
  // left, z up; m): the nose, and the rotors at (±ROTOR_M, ±ROTOR_M).
  const NOSE = { at_m: [0.12, 0, 0.03], size_m: [0.1, 0.07, 0.03] };
  const ROTOR_M = 0.177;
  // The top view's framing, which the CI's pixel probes compute independently: the bounding
  // box of the gate centres (x, y) grown by FRAMING.margin_m on every side, fitted into the
  // canvas at one scale (pixels per metre) for both axes, centred; x to the right, y up.
  const FRAMING = { margin_m: 2.0 };

  const fail = (message) => {
    document.body.dataset.error = String(message);
    const el = document.getElementById('hud');
    if (el) el.textContent = 'replay error: ' + message;
  };
  window.addEventListener('error', (e) => fail(e.message));

  const data = JSON.parse(document.getElementById('replay-data').textContent);
  const dt = data.dt_s;
  const params = Object.fromEntries(location.hash.replace(/^#/, '').split('&')
    .filter(Boolean).map((kv) => { const i = kv.indexOf('='); return i < 0 ? [kv, '1'] : [kv.slice(0, i), decodeURIComponent(kv.slice(i + 1))]; }));
  const probe = params.probe === '1';
  if (probe) document.body.classList.add('probe');

  // ---- data -------------------------------------------------------------------------
  function decodeF32(b64) {
    const bin = atob(b64);
    const view = new DataView(new ArrayBuffer(bin.length));
    for (let i = 0; i < bin.length; i++) view.setUint8(i, bin.charCodeAt(i));
    const out = new Float32Array(bin.length / 4);
    for (let i = 0; i < out.length; i++) out[i] = view.getFloat32(4 * i, true);
    return out;
  }
  const decoded = new Map();
  function episode(i) {
    if (!decoded.has(i)) {
      const e = data.episodes[i];
      decoded.set(i, {
        raw: e, steps: e.steps,
        states: { ego: decodeF32(e.ego), opponent: e.opponent ? decodeF32(e.opponent) : null },
        lead: e.lead_m ? decodeF32(e.lead_m) : null,
        respawnSet: new Set(e.respawns),
      });
    }
    return decoded.get(i);
  }
  const race = data.episodes.some((e) => e.opponent);
  const drones = race ? DRONES : DRONES.slice(0, 1);

  // ---- the page ---------------------------------------------------------------------
  document.body.insertAdjacentHTML('beforeend', `
    <div id="app">
      <div id="bar">
        <h1></h1>
        <div class="group"><button id="play" title="space">▶</button>
          <select id="speed" title="+ / -"><option>0.25</option><option>0.5</option><option selected>1</option><option>2</option><option>4</option></select>×</div>
        <div class="group">episode <select id="episode" title="n / p"></select></div>
        <div class="group" id="views"><button data-view="chase" title="1">chase</button><button data-view="orbit" title="2">orbit</button><button data-view="top" title="3">top</button></div>
        <div class="group"><button id="prev" title="[">◀ event</button><button id="next" title="]">event ▶</button></div>
      </div>
      <div id="view"><div id="hud"></div><div id="flash"></div>
        <div id="help">space play · ←/→ step (shift: 1 s) · [ ] events · 1 2 3 views · n/p episode · drag to orbit</div></div>
      <div id="side"></div>
      <div id="time"><canvas></canvas></div>
    </div>`);
  const $ = (s) => document.querySelector(s);
  $('#bar h1').textContent = data.title;
  data.episodes.forEach((e, i) => {
    const o = document.createElement('option');
    const m = e.metrics;
    o.value = i;
    o.textContent = e.opponent ? `${i} (${m.sustained_overtakes}/${m.overtakes} overtakes held)` : `${i} (${m.lap_times_s.length} laps, ${m.crashes} crashes)`;
    $('#episode').appendChild(o);
  });

  // ---- the scene ----------------------------------------------------------------------
  const viewEl = $('#view');
  const renderer = new THREE.WebGLRenderer({ antialias: !probe, preserveDrawingBuffer: true });
  renderer.setPixelRatio(probe ? 1 : Math.min(window.devicePixelRatio || 1, 2));
  viewEl.prepend(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(COLORS.background);
  const V = (a) => new THREE.Vector3(a[0], a[1], a[2]);

  const gates = data.track.gates;
  const bounds = gates.reduce((b, g) => ({
    x0: Math.min(b.x0, g.center_m[0]), x1: Math.max(b.x1, g.center_m[0]),
    y0: Math.min(b.y0, g.center_m[1]), y1: Math.max(b.y1, g.center_m[1]),
  }), { x0: Infinity, x1: -Infinity, y0: Infinity, y1: -Infinity });
  const centre = new THREE.Vector3((bounds.x0 + bounds.x1) / 2, (bounds.y0 + bounds.y1) / 2, 0);

  // Ground grid, 1 m.
  {
    const pts = [];
    const x0 = Math.floor(bounds.x0 - 4), x1 = Math.ceil(bounds.x1 + 4);
    const y0 = Math.floor(bounds.y0 - 4), y1 = Math.ceil(bounds.y1 + 4);
    for (let x = x0; x <= x1; x++) pts.push(x, y0, 0, x, y1, 0);
    for (let y = y0; y <= y1; y++) pts.push(x0, y, 0, x1, y, 0);
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.Float32BufferAttribute(pts, 3));
    scene.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: COLORS.grid })));
  }
  // The referee's centre line.
  {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.Float32BufferAttribute(data.track.centerline_m.flat(), 3));
    const line = new THREE.Line(g, new THREE.LineDashedMaterial({ color: COLORS.centerline, dashSize: 0.3, gapSize: 0.2 }));
    line.computeLineDistances();
    scene.add(line);
  }
  function label(text, color) {
    const c = document.createElement('canvas');
    c.width = 128; c.height = 64;
    const ctx = c.getContext('2d');
    ctx.font = 'bold 40px system-ui, sans-serif';
    ctx.textAlign = 'center'; ctx.textBaseline = 'middle';
    ctx.fillStyle = color; ctx.fillText(text, 64, 34);
    const s = new THREE.Sprite(new THREE.SpriteMaterial({ map: new THREE.CanvasTexture(c), depthWrite: false }));
    s.scale.set(0.8, 0.4, 1);
    return s;
  }
  // Gates: a square frame around the opening, in the gate's frame (+x through it).
  const h = data.track.opening_half_size_m, b = GATE_BAR_M;
  const gateMaterial = new THREE.MeshBasicMaterial({ color: COLORS.gate });
  const labelled = new Map();
  gates.forEach((gate, i) => {
    const group = new THREE.Group();
    const bar = (sy, sz, y, z) => {
      const m = new THREE.Mesh(new THREE.BoxGeometry(0.06, sy, sz), gateMaterial);
      m.position.set(0, y, z);
      group.add(m);
    };
    bar(2 * h + 2 * b, b, 0, h + b / 2);
    bar(2 * h + 2 * b, b, 0, -h - b / 2);
    bar(b, 2 * h, h + b / 2, 0);
    bar(b, 2 * h, -h - b / 2, 0);
    // A chevron on the exit side, level with the top bar: the direction of travel.
    const chevron = new THREE.BufferGeometry();
    const zc = h + b;
    chevron.setAttribute('position', new THREE.Float32BufferAttribute([0.35, 0.3, zc, 0.65, 0, zc, 0.65, 0, zc, 0.35, -0.3, zc], 3));
    group.add(new THREE.LineSegments(chevron, new THREE.LineBasicMaterial({ color: COLORS.gate })));
    group.position.copy(V(gate.center_m));
    if (!probe) {
      // Above the frame; gates that share a place (the figure-8's crossing) stack their labels.
      const place = gate.center_m.slice(0, 2).map((c) => c.toFixed(1)).join();
      const stacked = labelled.get(place) || 0;
      labelled.set(place, stacked + 1);
      const l = label('g' + i, COLORS.gate);
      l.position.copy(group.position).add(new THREE.Vector3(0, 0, h + b + 0.3 + 0.4 * stacked));
      scene.add(l);
    }
    const f = gate.frame;
    group.quaternion.set(f[1], f[2], f[3], f[0]);
    scene.add(group);
  });

  // Drones: an X frame, rotors, a white nose on +x.
  function makeDrone(color) {
    const group = new THREE.Group();
    const mat = (c) => new THREE.MeshBasicMaterial({ color: c });
    const add = (geometry, material, order, setup) => {
      const m = new THREE.Mesh(geometry, material);
      m.renderOrder = order;
      setup(m);
      group.add(m);
    };
    const arm = mat(color);
    add(new THREE.BoxGeometry(0.5, 0.04, 0.02), arm, 10, (m) => { m.rotation.z = Math.PI / 4; });
    add(new THREE.BoxGeometry(0.5, 0.04, 0.02), arm, 10, (m) => { m.rotation.z = -Math.PI / 4; });
    for (const [sx, sy] of [[1, 1], [1, -1], [-1, 1], [-1, -1]]) {
      add(new THREE.CylinderGeometry(0.085, 0.085, 0.012, 20), mat(COLORS.rotor), 11, (m) => {
        m.rotation.x = Math.PI / 2; m.position.set(sx * ROTOR_M, sy * ROTOR_M, 0.015);
      });
    }
    add(new THREE.BoxGeometry(0.16, 0.16, 0.05), mat(color), 12, () => {});
    add(new THREE.BoxGeometry(NOSE.size_m[0], NOSE.size_m[1], NOSE.size_m[2]), mat(COLORS.nose), 13, (m) => { m.position.set(...NOSE.at_m); });
    scene.add(group);
    return group;
  }
  // A drone's path. Drawn after the scene and before the drones (renderOrder 9; the drones'
  // parts are 10-13), without writing depth: a gate in front still hides it, but it never
  // hides a drone, not even its own rotors under the trail it left while descending.
  function makeLine(color, opacity) {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.Float32BufferAttribute(new Float32Array(3), 3));
    const line = new THREE.LineSegments(g, new THREE.LineBasicMaterial({
      color, transparent: opacity < 1, opacity, depthWrite: false,
    }));
    line.renderOrder = 9;
    line.frustumCulled = false;
    scene.add(line);
    return line;
  }
  const actors = drones.map((d) => ({
    ...d,
    body: makeDrone(COLORS[d.key]),
    trail: makeLine(COLORS[d.key + 'Trail'], 1),
    ghost: makeLine(COLORS[d.key], 0.16),
  }));
  // The probe view shows the moment alone: no other flights' paths over the drones.
  if (probe) for (const a of actors) a.ghost.visible = false;
  const crashGroup = new THREE.Group();
  scene.add(crashGroup);

  // Cameras.
  const perspective = new THREE.PerspectiveCamera(55, 1, 0.05, 300);
  perspective.up.set(0, 0, 1);
  perspective.position.set(centre.x, centre.y - 16, 11);
  const top = new THREE.OrthographicCamera(-1, 1, 1, -1, 0.1, 200);
  top.position.set(centre.x, centre.y, 80);
  top.up.set(0, 1, 0);
  top.lookAt(centre.x, centre.y, 0);
  const controls = new THREE.OrbitControls(perspective, renderer.domElement);
  controls.target.copy(centre);
  controls.enableDamping = false;
  controls.update();

  // ---- state ------------------------------------------------------------------------
  const state = {
    episode: 0, t: dt, playing: false, speed: 1, view: 'chase', chaseDir: new THREE.Vector3(1, 0, 0),
  };
  const ep = () => episode(state.episode);
  const duration = () => ep().steps * dt;
  // Index of the recorded step shown at time t: the state after step k + 1 is at (k + 1) dt.
  const stepAt = (t) => Math.min(ep().steps - 1, Math.max(0, Math.round(t / dt) - 1));

  function pose(key, t) {
    const e = ep(), s = e.states[key];
    const x = t / dt - 1;
    const k = Math.min(e.steps - 1, Math.max(0, Math.floor(x + 1e-6)));
    const k1 = Math.min(e.steps - 1, k + 1);
    const f = (k1 === k || e.respawnSet.has(k + 1)) ? 0 : Math.min(1, Math.max(0, x - k));
    const at = (i, j) => stateAt(s, i, j);
    const p = new THREE.Vector3(at(k, 0), at(k, 1), at(k, 2));
    const q = new THREE.Quaternion(at(k, 4), at(k, 5), at(k, 6), at(k, 3));
    if (f > 0) {
      p.lerp(new THREE.Vector3(at(k1, 0), at(k1, 1), at(k1, 2)), f);
      q.slerp(new THREE.Quaternion(at(k1, 4), at(k1, 5), at(k1, 6), at(k1, 3)), f);
    }
    return { p, q, speed: at(k, 7), k };
  }
  // Segments [k, k+1] of a drone's path between steps a and b, skipping respawns.
  function segments(key, a, b) {
    const e = ep(), s = e.states[key], out = [];
    for (let k = Math.max(0, a); k < Math.min(b, e.steps - 1); k++) {
      if (e.respawnSet.has(k + 1)) continue;
      for (const i of [k, k + 1]) out.push(stateAt(s, i, 0), stateAt(s, i, 1), stateAt(s, i, 2));
    }
    return out;
  }
  function setLine(line, pts) {
    line.geometry.setAttribute('position', new THREE.Float32BufferAttribute(pts.length ? pts : [0, 0, -100, 0, 0, -100], 3));
  }

  // Every event of the episode with its time and words, for the timeline and the list.
  function events() {
    const e = ep().raw, out = [];
    for (const ev of e.events) {
      const who = DRONES[ev.drone].name;
      if (ev.gate !== undefined) out.push({ t: ev.step * dt, kind: 'gate', drone: ev.drone, text: `${who} passes g${ev.gate}` });
      else out.push({ t: ev.step * dt, kind: 'crash', drone: ev.drone, text: `${who} ${ev.crash}` });
    }
    for (const o of e.overtakes) out.push({ t: o.step * dt, kind: o.sustained ? 'overtake-sustained' : 'overtake', drone: 0, text: o.sustained ? 'ego overtakes (held 2 s)' : 'ego overtakes (not held)' });
    for (const r of e.respawns) out.push({ t: r * dt, kind: 'restart', drone: -1, text: 'restart (both respawn)' });
    // At equal times a restart sorts before the crash that caused it, so the overlay (the
    // last recent event) names the crash.
    return out.sort((a, b) => a.t - b.t || (b.kind === 'restart') - (a.kind === 'restart'));
  }
  let episodeEvents = [];

  function loadEpisode(i) {
    state.episode = Math.max(0, Math.min(data.episodes.length - 1, i));
    $('#episode').value = state.episode;
    episodeEvents = events();
    for (const a of actors) setLine(a.ghost, segments(a.key, 0, ep().steps));
    crashGroup.clear();
    for (const ev of episodeEvents.filter((x) => x.kind === 'crash')) {
      const k = stepAt(ev.t), s = ep().states[DRONES[ev.drone].key];
      const m = new THREE.Mesh(new THREE.BoxGeometry(0.18, 0.18, 0.18), new THREE.MeshBasicMaterial({ color: COLORS.crash }));
      m.position.set(stateAt(s, k, 0), stateAt(s, k, 1), stateAt(s, k, 2));
      m.rotation.set(0.6, 0.6, 0);
      m.userData.t = ev.t;
      crashGroup.add(m);
    }
    buildSide();
    state.t = Math.min(state.t, duration());
  }

  // ---- side panel: who, the episode's numbers, speed and lead, the events -------------
  function buildSide() {
    const m = ep().raw.metrics;
    const laps = m.lap_times_s.length ? `${m.lap_times_s.length} (best ${Math.min(...m.lap_times_s).toFixed(2)} s)` : 'none';
    const rows = [['laps', laps], ['ego crashes', m.crashes]];
    if (race) rows.push(['opponent crashes', m.opponent_crashes], ['overtakes (held 2 s)', `${m.overtakes} (${m.sustained_overtakes})`], ['flights won', `${m.flights_won} of ${m.flights}`]);
    $('#side').innerHTML = `
      <h2>Pilots</h2>
      ${drones.map((d, i) => `<div title="${escape(data.pilots[i] || '')}"><span class="swatch" style="background:${COLORS[d.key]}"></span>${d.name}: ${escape(shortName(data.pilots[i] || ''))}</div>`).join('')}
      <div style="color:var(--dim)">${escape(data.preset)} preset, seed ${data.seed}, episode ${state.episode}</div>
      <h2>Episode</h2>
      <table class="metrics">${rows.map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join('')}</table>
      <h2>Speed (m/s)</h2><canvas class="chart" id="speed-chart"></canvas>
      ${race ? '<h2>Ego lead along the track (m)</h2><canvas class="chart" id="lead-chart"></canvas>' : ''}
      <h2>Events</h2><div id="events"></div>`;
    for (const c of document.querySelectorAll('canvas.chart')) {
      c.addEventListener('mousedown', (e) => seekFromX(c, e));
      c.addEventListener('mousemove', (e) => { if (e.buttons) seekFromX(c, e); });
    }
    const list = $('#events');
    for (const ev of episodeEvents) {
      const d = document.createElement('div');
      d.dataset.t = ev.t;
      const color = ev.kind === 'crash' ? COLORS.crash : ev.kind.startsWith('overtake') ? COLORS.gold : ev.drone >= 0 ? COLORS[DRONES[ev.drone].key] : COLORS.centerline;
      d.innerHTML = `<span class="swatch" style="background:${color}"></span>${ev.t.toFixed(2)} s  ${escape(ev.text)}`;
      d.addEventListener('click', () => { state.t = Math.max(dt, ev.t - 0.5); state.playing = false; });
      list.appendChild(d);
    }
  }
  // A pilot's file name without its directories ("/a/b/stage1.blob (stage1)" -> "stage1.blob (stage1)").
  function shortName(s) { return String(s).replace(/^[^ ]*[\/\\]/, ''); }
  function escape(s) { return String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' }[c])); }
  function seekFromX(canvas, e) {
    const r = canvas.getBoundingClientRect();
    state.t = Math.max(dt, Math.min(duration(), (e.clientX - r.left) / r.width * duration()));
  }
  function sized(canvas) {
    const r = canvas.getBoundingClientRect(), px = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(r.width * px) || canvas.height !== Math.round(r.height * px)) {
      canvas.width = Math.round(r.width * px); canvas.height = Math.round(r.height * px);
    }
    const ctx = canvas.getContext('2d');
    ctx.setTransform(px, 0, 0, px, 0, 0);
    return { ctx, w: r.width, h: r.height };
  }
  function chart(canvas, series, zeroLine) {
    if (!canvas) return;
    const { ctx, w, h } = sized(canvas);
    ctx.clearRect(0, 0, w, h);
    const e = ep(), n = e.steps;
    let lo = Infinity, hi = -Infinity;
    for (const s of series) for (let k = 0; k < n; k++) { const v = s.at(k); if (Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); } }
    if (!Number.isFinite(lo)) return;
    if (zeroLine) { lo = Math.min(lo, 0); hi = Math.max(hi, 0); }
    if (hi - lo < 1e-6) hi = lo + 1;
    const pad = 14;
    const X = (k) => (k + 1) / n * w, Y = (v) => pad + (hi - v) / (hi - lo) * (h - 2 * pad);
    ctx.strokeStyle = COLORS.grid; ctx.fillStyle = COLORS.centerline; ctx.font = '10px system-ui, sans-serif';
    for (const v of [lo, hi, ...(zeroLine ? [0] : [])]) {
      ctx.beginPath(); ctx.moveTo(0, Y(v)); ctx.lineTo(w, Y(v)); ctx.stroke();
      ctx.fillText(v.toFixed(1), 2, Y(v) - 2);
    }
    ctx.strokeStyle = '#444b57';
    for (const r of e.raw.respawns) { ctx.beginPath(); ctx.moveTo(X(r - 1), 0); ctx.lineTo(X(r - 1), h); ctx.stroke(); }
    for (const s of series) {
      ctx.strokeStyle = s.color; ctx.lineWidth = 1.3; ctx.beginPath();
      let pen = false;
      for (let k = 0; k < n; k++) {
        const v = s.at(k);
        if (!Number.isFinite(v) || e.respawnSet.has(k)) { pen = false; if (!Number.isFinite(v)) continue; }
        if (pen) ctx.lineTo(X(k), Y(v)); else { ctx.moveTo(X(k), Y(v)); pen = true; }
      }
      ctx.stroke(); ctx.lineWidth = 1;
    }
    const x = state.t / duration() * w;
    ctx.strokeStyle = '#ffffff'; ctx.beginPath(); ctx.moveTo(x, 0); ctx.lineTo(x, h); ctx.stroke();
  }
  function drawCharts() {
    const e = ep();
    chart($('#speed-chart'), actors.map((a) => ({ color: COLORS[a.key], at: (k) => stateAt(e.states[a.key], k, 7) })), false);
    if (e.lead) chart($('#lead-chart'), [{ color: COLORS.ego, at: (k) => e.lead[k] }], true);
    for (const d of document.querySelectorAll('#events div')) d.classList.toggle('future', Number(d.dataset.t) > state.t);
  }
  // ---- the timeline: events over the episode, the cursor ------------------------------
  const timeCanvas = $('#time canvas');
  function drawTimeline() {
    const { ctx, w, h } = sized(timeCanvas);
    ctx.clearRect(0, 0, w, h);
    const T = duration(), X = (t) => 8 + t / T * (w - 16), mid = h / 2;
    ctx.fillStyle = '#232831'; ctx.fillRect(8, mid - 16, w - 16, 32);
    ctx.fillStyle = COLORS.centerline; ctx.font = '10px system-ui, sans-serif';
    for (let s = 0; s <= T; s += 5) { ctx.fillRect(X(s), h - 12, 1, 4); ctx.fillText(s + ' s', X(s) + 2, h - 2); }
    for (const ev of episodeEvents) {
      const x = X(ev.t);
      if (ev.kind === 'gate') {
        ctx.fillStyle = COLORS[DRONES[ev.drone].key];
        ctx.fillRect(x - 0.5, ev.drone === 0 ? mid - 14 : mid + 2, 1.5, 12);
      } else if (ev.kind === 'restart') {
        ctx.fillStyle = '#8a93a3'; ctx.fillRect(x - 0.5, mid - 20, 1, 40);
      } else if (ev.kind === 'crash') {
        ctx.strokeStyle = COLORS.crash; ctx.lineWidth = 2; ctx.beginPath();
        const y = ev.drone === 0 ? mid - 26 : mid + 26;
        ctx.moveTo(x - 4, y - 4); ctx.lineTo(x + 4, y + 4); ctx.moveTo(x + 4, y - 4); ctx.lineTo(x - 4, y + 4); ctx.stroke(); ctx.lineWidth = 1;
      } else {
        ctx.beginPath(); ctx.moveTo(x, mid - 20); ctx.lineTo(x - 6, mid - 32); ctx.lineTo(x + 6, mid - 32); ctx.closePath();
        if (ev.kind === 'overtake-sustained') { ctx.fillStyle = COLORS.gold; ctx.fill(); } else { ctx.strokeStyle = COLORS.gold; ctx.stroke(); }
      }
    }
    const x = X(state.t);
    ctx.fillStyle = '#ffffff'; ctx.fillRect(x - 1, 2, 2, h - 14);
  }
  const seekTimeline = (e) => { const r = timeCanvas.getBoundingClientRect(); state.t = Math.max(dt, Math.min(duration(), (e.clientX - r.left - 8) / (r.width - 16) * duration())); };
  timeCanvas.addEventListener('mousedown', seekTimeline);
  timeCanvas.addEventListener('mousemove', (e) => { if (e.buttons) seekTimeline(e); });

  // ---- each frame ---------------------------------------------------------------------
  function framing(w, hgt) {
    const bw = bounds.x1 - bounds.x0 + 2 * FRAMING.margin_m, bh = bounds.y1 - bounds.y0 + 2 * FRAMING.margin_m;
    const scale = Math.min(w / bw, hgt / bh);
    return { scale, cx: centre.x, cy: centre.y };
  }
  function place() {
    for (const m of crashGroup.children) m.visible = m.userData.t <= state.t + 1e-9;
    const poses = {};
    for (const a of actors) {
      const ps = pose(a.key, state.t);
      poses[a.key] = ps;
      a.body.position.copy(ps.p);
      a.body.quaternion.copy(ps.q);
      // The trail: the last TRAIL_S seconds since the last restart.
      const restart = ep().raw.respawns.filter((r) => r - 1 < ps.k).pop() || 0;
      setLine(a.trail, segments(a.key, Math.max(restart, ps.k - Math.round(TRAIL_S / dt)), ps.k));
    }
    return poses;
  }
  function hud(poses) {
    const e = ep(), k = poses.ego.k;
    const parts = [`<span class="big">${state.t.toFixed(2)} s</span> / ${duration().toFixed(0)} s`];
    for (const a of actors) parts.push(`<span class="swatch" style="background:${COLORS[a.key]}"></span>${a.name} ${poses[a.key].speed.toFixed(1)} m/s`);
    if (e.lead) { const l = e.lead[k]; parts.push(Number.isFinite(l) ? `lead ${l >= 0 ? '+' : ''}${l.toFixed(2)} m` : 'lead —'); }
    $('#hud').innerHTML = parts.join('<br>');
    const recent = episodeEvents.filter((ev) => ev.kind !== 'gate' && ev.t <= state.t && state.t - ev.t < 1.5).pop();
    const flash = $('#flash');
    if (recent) {
      flash.style.display = 'block';
      flash.style.color = recent.kind === 'crash' ? COLORS.crash : recent.kind.startsWith('overtake') ? COLORS.gold : COLORS.gate;
      flash.textContent = recent.text;
    } else flash.style.display = 'none';
  }
  function camera(poses, w, hgt) {
    if (state.view === 'top') {
      const f = framing(w, hgt);
      top.left = -w / 2 / f.scale; top.right = w / 2 / f.scale; top.top = hgt / 2 / f.scale; top.bottom = -hgt / 2 / f.scale;
      top.updateProjectionMatrix();
      return top;
    }
    perspective.aspect = w / Math.max(1, hgt);
    perspective.updateProjectionMatrix();
    if (state.view === 'chase') {
      const e = ep(), s = e.states.ego, k = poses.ego.k;
      const restart = e.raw.respawns.filter((r) => r <= k).pop() || 0;
      const k0 = Math.max(restart, k - 5);
      const d = new THREE.Vector3(stateAt(s, k, 0) - stateAt(s, k0, 0), stateAt(s, k, 1) - stateAt(s, k0, 1), 0);
      if (d.length() > 0.05) state.chaseDir.lerp(d.normalize(), 0.25).normalize();
      // Behind the ego; with the opponent near, behind the pair, backed off to hold both.
      const target = poses.ego.p.clone();
      let back = 2.6;
      if (poses.opponent) {
        const d = target.distanceTo(poses.opponent.p), w = Math.min(1, Math.max(0, (6 - d) / 2));
        target.lerp(poses.opponent.p, 0.5 * w);
        back += 0.8 * d * w;
      }
      perspective.position.copy(target).addScaledVector(state.chaseDir, -back).add(new THREE.Vector3(0, 0, 0.6 + 0.15 * back));
      perspective.lookAt(target.clone().addScaledVector(state.chaseDir, 1.5));
    } else controls.update();
    return perspective;
  }
  let last = null;
  function frame(now) {
    if (state.playing && last !== null) {
      state.t += (now - last) / 1000 * state.speed;
      if (state.t >= duration()) { state.t = duration(); state.playing = false; }
    }
    last = now;
    $('#play').textContent = state.playing ? '❚❚' : '▶';
    const w = viewEl.clientWidth, hgt = viewEl.clientHeight;
    const px = renderer.getPixelRatio();
    if (renderer.domElement.width !== Math.round(w * px) || renderer.domElement.height !== Math.round(hgt * px)) renderer.setSize(w, hgt, false);
    const poses = place();
    controls.enabled = state.view === 'orbit';
    renderer.render(scene, camera(poses, w, hgt));
    if (!probe) { hud(poses); drawCharts(); drawTimeline(); }
    if (!document.body.dataset.ready) {
      const f = framing(w, hgt);
      window.replayView = { width: w, height: hgt, scale_px_per_m: f.scale, centre_m: [f.cx, f.cy], t: state.t, episode: state.episode };
      document.body.dataset.ready = '1';
    }
    requestAnimationFrame(frame);
  }

  // ---- controls ---------------------------------------------------------------------
  function setView(v) {
    state.view = v;
    for (const b of document.querySelectorAll('#views button')) b.classList.toggle('on', b.dataset.view === v);
  }
  function jumpEvent(dir) {
    const marks = episodeEvents.filter((ev) => ev.kind !== 'gate');
    const next = dir > 0 ? marks.find((ev) => ev.t - 0.5 > state.t + 1e-6) : marks.filter((ev) => ev.t - 0.5 < state.t - 1e-6).pop();
    if (next) { state.t = Math.max(dt, next.t - 0.5); state.playing = false; }
  }
  $('#play').addEventListener('click', () => { if (state.t >= duration()) state.t = dt; state.playing = !state.playing; });
  $('#speed').addEventListener('change', (e) => { state.speed = Number(e.target.value); });
  $('#episode').addEventListener('change', (e) => loadEpisode(Number(e.target.value)));
  for (const b of document.querySelectorAll('#views button')) b.addEventListener('click', () => setView(b.dataset.view));
  $('#prev').addEventListener('click', () => jumpEvent(-1));
  $('#next').addEventListener('click', () => jumpEvent(1));
  window.addEventListener('keydown', (e) => {
    if (e.target.tagName === 'SELECT') return;
    const step = e.shiftKey ? 1 : dt;
    const speeds = [0.25, 0.5, 1, 2, 4];
    switch (e.key) {
      case ' ': $('#play').click(); break;
      case 'ArrowRight': state.t = Math.min(duration(), state.t + step); state.playing = false; break;
      case 'ArrowLeft': state.t = Math.max(dt, state.t - step); state.playing = false; break;
      case ']': jumpEvent(1); break;
      case '[': jumpEvent(-1); break;
      case '1': setView('chase'); break;
      case '2': setView('orbit'); break;
      case '3': setView('top'); break;
      case 'n': loadEpisode(state.episode + 1); break;
      case 'p': loadEpisode(state.episode - 1); break;
      case '+': case '=': state.speed = speeds[Math.min(4, speeds.indexOf(state.speed) + 1)]; $('#speed').value = state.speed; break;
      case '-': state.speed = speeds[Math.max(0, speeds.indexOf(state.speed) - 1)]; $('#speed').value = state.speed; break;
      default: return;
    }
    e.preventDefault();
  });

  // ---- start: the URL's options ------------------------------------------------------
  const finite = (v, fallback) => (Number.isFinite(Number(v)) ? Number(v) : fallback);
  let start = { episode: Math.trunc(finite(params.episode, 0)), t: null };
  if (params.t === 'overtake') {
    // The first sustained overtake (of the given episode, else of any), else the first one.
    const order = params.episode !== undefined ? [start.episode] : data.episodes.map((_, i) => i);
    const find = (held) => { for (const i of order) { const o = data.episodes[i].overtakes.find((m) => !held || m.sustained); if (o) return { episode: i, t: o.step * dt }; } return null; };
    start = find(true) || find(false) || { episode: start.episode, t: null };
    if (start.t !== null) start.t += finite(params.offset, 0);
  } else if (params.t !== undefined) start.t = finite(params.t, null);
  loadEpisode(start.episode);
  state.t = Math.max(dt, Math.min(duration(), start.t === null ? dt : start.t));
  setView(probe ? 'top' : (params.view || 'chase'));
  state.speed = [0.25, 0.5, 1, 2, 4].includes(Number(params.speed)) ? Number(params.speed) : 1;
  $('#speed').value = state.speed;
  state.playing = params.play === '1';
  requestAnimationFrame(frame);
}
