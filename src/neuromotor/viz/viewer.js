// neuromotor viewer: draws the run inlined in #nm-data (built by neuromotor/viz/html.py).
// All positions are already in three.js's Y-up frame; quaternions are x y z w.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const D = JSON.parse(document.getElementById('nm-data').textContent);
const $ = (id) => document.getElementById(id);

// ---------------------------------------------------------------------------------------------
// Data
// ---------------------------------------------------------------------------------------------

const TYPED = { float32: Float32Array, float64: Float64Array, uint32: Uint32Array, uint8: Uint8Array };

function unpack(a) {
  if (!a) return null;
  const bytes = Uint8Array.from(atob(a.b64), (c) => c.charCodeAt(0));
  return new TYPED[a.dtype](bytes.buffer);
}

const time = unpack(D.time);
const T = time.length;
const dev = unpack(D.deviation);
const rgb = (c) => new THREE.Color().setRGB(c[0], c[1], c[2], THREE.SRGBColorSpace);  // style.py's colours are sRGB
const COLORS = D.meta.colors;

function nearestIndex(t) {
  let lo = 0, hi = T - 1;
  if (t <= time[0]) return 0;
  if (t >= time[hi]) return hi;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (time[mid] <= t) lo = mid; else hi = mid;
  }
  return (t - time[lo] <= time[hi] - t) ? lo : hi;
}

// ---------------------------------------------------------------------------------------------
// Scene
// ---------------------------------------------------------------------------------------------

const canvas = $('nm-canvas');
// three.js needs WebGL 2. Without it (no GPU and no software GL, or WebGL turned off) the page
// says so where the picture would be and still draws the curve and the timeline.
function hasWebGL2() {
  try { return !!document.createElement('canvas').getContext('webgl2'); } catch (e) { return false; }
}
let renderer = null;
if (hasWebGL2()) {
  try {
    renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
  } catch (e) {
    renderer = null;
  }
}
if (!renderer) {
  canvas.style.display = 'none';
  $('nm-no-webgl').hidden = false;
}
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xf4f5f7);
const camera = new THREE.PerspectiveCamera(D.view.fov, 1, 0.02, 200);
camera.position.fromArray(D.view.position);
const controls = new OrbitControls(camera, canvas);
controls.target.fromArray(D.view.target);
controls.update();

scene.add(new THREE.HemisphereLight(0xffffff, 0x8a8a80, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(2, 4, 3);
scene.add(sun);

const layers = {
  character: new THREE.Group(), ghost: new THREE.Group(), forces: new THREE.Group(),
  ball: new THREE.Group(), grid: new THREE.Group(),
};
Object.values(layers).forEach((g) => scene.add(g));

// The ghost is pushed back in depth: where it coincides with the character it stays hidden
// (instead of paling it), and it shows where the two motions differ.
function figureMaterial(color, ghost) {
  return new THREE.MeshStandardMaterial({
    color: rgb(color), roughness: 0.65, metalness: 0.0, flatShading: true,
    transparent: ghost, opacity: ghost ? 0.45 : 1.0, depthWrite: !ghost,
    polygonOffset: ghost, polygonOffsetFactor: 4, polygonOffsetUnits: 16,
  });
}
const MAT = { character: figureMaterial(COLORS.perturbed, false), ghost: figureMaterial(COLORS.ghost, true) };

const UP = new THREE.Vector3(0, 1, 0);
const _a = new THREE.Vector3(), _b = new THREE.Vector3(), _d = new THREE.Vector3();

// Body polyhedra: one mesh per body, moved rigidly by its pose.
function bodyMeshes(shapes, material, group) {
  const verts = unpack(shapes.vertices), index = unpack(shapes.index);
  return shapes.ranges.map(([v0, nv, i0, ni]) => {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(verts.slice(3 * v0, 3 * (v0 + nv)), 3));
    g.setIndex(new THREE.BufferAttribute(index.slice(i0, i0 + ni), 1));
    g.computeVertexNormals();
    const m = new THREE.Mesh(g, material);
    group.add(m);
    return m;
  });
}

// Capsules along bones (detail bones, or every bone of a run without shapes), made as long as
// the bone at the first sample (bones are rigid; a small stretch later is absorbed by scaling).
function capsuleMeshes(caps, points, material, group) {
  const edges = unpack(caps.edges), radii = unpack(caps.radii);
  const meshes = [];
  for (let e = 0; e < radii.length; e++) {
    const i = edges[2 * e], j = edges[2 * e + 1];
    const len = Math.max(_a.fromArray(points, 3 * i).distanceTo(_b.fromArray(points, 3 * j)), 1e-6);
    const m = new THREE.Mesh(new THREE.CapsuleGeometry(radii[e], len, 4, 10), material);
    m.userData = { ends: [i, j], length: len };
    group.add(m);
    meshes.push(m);
  }
  return meshes;
}

// Put a Y-aligned object centred at the origin midway between a and b, its Y along b - a;
// returns |b - a|.
function spanBetween(obj, a, b) {
  _d.subVectors(b, a);
  const len = _d.length();
  obj.position.addVectors(a, b).multiplyScalar(0.5);
  if (len > 1e-9) obj.quaternion.setFromUnitVectors(UP, _d.divideScalar(len));
  return len;
}

const shapes = D.shapes;
const figures = ['character', 'ghost'].map((name) => {
  const ghost = name === 'ghost';
  const fig = { bodies: [], capsules: [] };
  if (shapes) {
    fig.bodies = bodyMeshes(shapes, MAT[name], layers[name]);
    fig.pos = unpack(ghost ? shapes.pos_u : shapes.pos);
    fig.quat = unpack(ghost ? shapes.quat_u : shapes.quat);
  }
  if (D.capsules) {
    fig.points = unpack(ghost ? D.capsules.points_u : D.capsules.points);
    fig.nPoints = fig.points.length / (3 * T);
    fig.capsules = capsuleMeshes(D.capsules, fig.points, MAT[name], layers[name]);
  }
  return fig;
});

function poseFigure(fig, k) {
  const B = fig.bodies.length;
  for (let b = 0; b < B; b++) {
    fig.bodies[b].position.fromArray(fig.pos, 3 * (k * B + b));
    fig.bodies[b].quaternion.fromArray(fig.quat, 4 * (k * B + b));
  }
  for (const m of fig.capsules) {
    const [i, j] = m.userData.ends;
    _a.fromArray(fig.points, 3 * (k * fig.nPoints + i));
    _b.fromArray(fig.points, 3 * (k * fig.nPoints + j));
    m.scale.set(1, Math.max(spanBetween(m, _a, _b), 1e-6) / m.userData.length, 1);
  }
}

// Arrows: shaft and head, tail -> tip. The hit's force, and the balance assist's virtual force
// on the pelvis when the run had it on (help, not physics: drawn so that it is seen).
function arrowMeshes(color) {
  const mat = new THREE.MeshStandardMaterial({ color: rgb(color), roughness: 0.5 });
  const m = { shaft: new THREE.Mesh(new THREE.CylinderGeometry(0.012, 0.012, 1, 12), mat),
              head: new THREE.Mesh(new THREE.ConeGeometry(0.035, 0.09, 16), mat) };
  layers.forces.add(m.shaft, m.head);
  return m;
}

function poseArrowMeshes(m, tail, tip, k, on) {
  _a.fromArray(tail, 3 * k);
  _b.fromArray(tip, 3 * k);
  on = on && _a.distanceTo(_b) > 1e-6;
  m.shaft.visible = m.head.visible = on;
  if (!on) return;
  const headLen = Math.min(0.09, 0.5 * _a.distanceTo(_b));
  _d.subVectors(_b, _a).normalize();
  const neck = _b.clone().addScaledVector(_d, -headLen);
  m.shaft.scale.set(1, Math.max(spanBetween(m.shaft, _a, neck), 1e-6), 1);
  spanBetween(m.head, neck, _b);
  m.head.scale.set(1, Math.max(headLen, 1e-6) / 0.09, 1);
}

const F = D.force;
const fTail = unpack(F.tail), fTip = unpack(F.tip), fOn = unpack(F.on);
const forceArrow = arrowMeshes(COLORS.force);
const A = D.assist;
const assistArrow = A ? arrowMeshes(COLORS.assist) : null;
const aTail = A ? unpack(A.tail) : null, aTip = A ? unpack(A.tip) : null;

function poseArrow(k) {
  poseArrowMeshes(forceArrow, fTail, fTip, k, fOn[k] > 0);
  if (assistArrow) poseArrowMeshes(assistArrow, aTail, aTip, k, true);
}

// Ball.
let ball = null, ballPos = null;
if (D.ball) {
  ballPos = unpack(D.ball.pos);
  ball = new THREE.Mesh(new THREE.SphereGeometry(D.ball.radius, 32, 16),
                        new THREE.MeshStandardMaterial({ color: rgb(COLORS.ball), roughness: 0.4 }));
  layers.ball.add(ball);
} else {
  $('nm-ball-toggle').style.display = 'none';
}

// Ground grid at the lowest point of the run (1 line per GROUND_TILE_M).
const G = D.view.grid;
const grid = new THREE.GridHelper(G.size, G.divisions, 0x8c8c86, 0xb4b4ae);
grid.position.fromArray(G.center);
const ground = new THREE.Mesh(new THREE.PlaneGeometry(G.size, G.size),
                              new THREE.MeshBasicMaterial({ color: 0xe6e6e1, polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1 }));
ground.rotation.x = -Math.PI / 2;
ground.position.fromArray(G.center);
// A tilted ground turns about its pivot with the run: ground and grid in a group at the pivot.
const groundGroup = new THREE.Group();
const tilt = D.tilt ? { pivot: new THREE.Vector3().fromArray(D.tilt.pivot), quat: unpack(D.tilt.quat) } : null;
if (tilt) {
  groundGroup.position.copy(tilt.pivot);
  for (const m of [ground, grid]) m.position.sub(tilt.pivot);
}
groundGroup.add(ground, grid);
layers.grid.add(groundGroup);
// A platform carries the ground, and the tilt's pivot, along: the group's place per sample.
const platform = D.platform ? unpack(D.platform) : null;
const groundHome = groundGroup.position.clone();

// ---------------------------------------------------------------------------------------------
// Deviation curve (2-D canvas)
// ---------------------------------------------------------------------------------------------

const chart = $('nm-chart');
const PAD = { left: 52, right: 14, top: 20, bottom: 26 };

function niceStep(range, n) {
  const raw = range / Math.max(n, 1), p = Math.pow(10, Math.floor(Math.log10(raw)));
  const m = raw / p;
  return p * (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10);
}

function drawChart(k) {
  const dpr = window.devicePixelRatio || 1;
  const w = chart.clientWidth, h = chart.clientHeight;
  if (chart.width !== Math.round(w * dpr) || chart.height !== Math.round(h * dpr)) {
    chart.width = Math.round(w * dpr); chart.height = Math.round(h * dpr);
  }
  const c = chart.getContext('2d');
  c.setTransform(dpr, 0, 0, dpr, 0, 0);
  c.clearRect(0, 0, w, h);
  c.font = '11px system-ui, sans-serif';
  c.fillStyle = '#333';
  if (!dev) { c.fillText('no deviation curve: the run has no theta_unperturbed', PAD.left, h / 2); return; }
  let ymax = 0;
  for (let i = 0; i < T; i++) ymax = Math.max(ymax, dev[i]);
  ymax = ymax > 0 ? ymax * 1.1 : 1;
  const t0 = time[0], t1 = T > 1 ? time[T - 1] : time[0] + 1;
  const X = (t) => PAD.left + (t - t0) / (t1 - t0) * (w - PAD.left - PAD.right);
  const Y = (v) => h - PAD.bottom - v / ymax * (h - PAD.top - PAD.bottom);
  c.fillStyle = 'rgba(220, 30, 30, 0.12)';
  for (const [a, b] of D.meta.hits) c.fillRect(X(a), PAD.top, Math.max(X(b) - X(a), 2), h - PAD.top - PAD.bottom);
  drawAxes(c, w, h, X, Y, t0, t1, ymax);
  c.strokeStyle = 'rgb(230, 115, 51)';
  c.lineWidth = 2;
  c.beginPath();
  for (let i = 0; i < T; i++) (i ? c.lineTo : c.moveTo).call(c, X(time[i]), Y(dev[i]));
  c.stroke();
  c.strokeStyle = '#c00';
  c.lineWidth = 1.5;
  c.beginPath(); c.moveTo(X(time[k]), PAD.top); c.lineTo(X(time[k]), h - PAD.bottom); c.stroke();
  c.fillStyle = '#c00';
  c.beginPath(); c.arc(X(time[k]), Y(dev[k]), 3.5, 0, 2 * Math.PI); c.fill();
  c.fillText(dev[k].toFixed(2) + ' deg', Math.min(X(time[k]) + 6, w - 70), PAD.top + 12);
}

function drawAxes(c, w, h, X, Y, t0, t1, ymax) {
  c.strokeStyle = '#bbb'; c.lineWidth = 1; c.fillStyle = '#444';
  c.textAlign = 'right';
  const ys = niceStep(ymax, 4);
  for (let v = 0; v <= ymax + 1e-12; v += ys) {
    c.beginPath(); c.moveTo(PAD.left, Y(v)); c.lineTo(w - PAD.right, Y(v)); c.stroke();
    c.fillText(+v.toFixed(6) + '', PAD.left - 5, Y(v) + 4);
  }
  c.textAlign = 'center';
  const xs = niceStep(t1 - t0, 10);
  for (let t = Math.ceil(t0 / xs) * xs; t <= t1 + 1e-9; t += xs) {
    c.fillText(+t.toFixed(6) + '', X(t), h - PAD.bottom + 15);
  }
  c.textAlign = 'left';
  c.fillText('RMS joint deviation, perturbed - unperturbed (deg) vs time (s)', PAD.left, PAD.top - 6);
}

// ---------------------------------------------------------------------------------------------
// Time, playback and controls
// ---------------------------------------------------------------------------------------------

const state = { k: -1, t: time[0], playing: false, speed: 1, last: null };
const slider = $('nm-slider');
slider.max = String(T - 1);
const forceLabel = $('nm-force-label');

function showIndex(k) {
  state.k = k;
  for (const fig of figures) poseFigure(fig, k);
  poseArrow(k);
  if (ball) ball.position.fromArray(ballPos, 3 * k);
  if (tilt) groundGroup.quaternion.fromArray(tilt.quat, 4 * k);
  if (platform) groundGroup.position.set(groundHome.x + platform[3 * k], groundHome.y + platform[3 * k + 1],
                                         groundHome.z + platform[3 * k + 2]);
  slider.value = String(k);
  $('nm-time').textContent = 't = ' + time[k].toFixed(3) + ' s';
  $('nm-status').setAttribute('data-index', String(k));
  $('nm-status').setAttribute('data-time', time[k].toFixed(6));
  drawChart(k);
}

function renderNow() {
  if (!renderer) return;
  const view = $('nm-view');
  const w = view.clientWidth, h = view.clientHeight;
  const size = renderer.getSize(new THREE.Vector2());
  if (size.x !== w || size.y !== h) {
    renderer.setSize(w, h, false);
    camera.aspect = w / Math.max(h, 1);
    camera.updateProjectionMatrix();
  }
  renderer.render(scene, camera);
  placeForceLabel(w, h);
}

function placeForceLabel(w, h) {
  const on = fOn[state.k] > 0 && layers.forces.visible && F.label;
  forceLabel.style.display = on ? 'block' : 'none';
  if (!on) return;
  _a.fromArray(fTail, 3 * state.k).project(camera);
  forceLabel.textContent = F.label;
  forceLabel.style.left = ((_a.x + 1) / 2 * w + 4) + 'px';
  forceLabel.style.top = ((1 - _a.y) / 2 * h - 18) + 'px';
}

// The next frame: an animation frame, or a timer when none comes (a page that is not being
// painted, such as a headless browser's, still plays).
let frameRequested = false, frameId = 0, frameTimer = 0;
function requestRender() {
  if (frameRequested) return;
  frameRequested = true;
  frameId = requestAnimationFrame(tick);
  frameTimer = setTimeout(tick, 50);
}

function tick() {
  const now = performance.now();   // one clock for both (a headless browser's frame times differ)
  cancelAnimationFrame(frameId);
  clearTimeout(frameTimer);
  frameRequested = false;
  if (state.playing) {
    if (state.last !== null) {
      state.t += (now - state.last) / 1000 * state.speed;
      if (state.t > time[T - 1]) state.t = time[0];
    }
    state.last = now;
    const k = nearestIndex(state.t);
    if (k !== state.k) showIndex(k);
    requestRender();
  }
  renderNow();
}

function setPlaying(on) {
  state.playing = on && T > 1;
  state.last = null;
  $('nm-play').textContent = state.playing ? 'Pause' : 'Play';
  requestRender();
}

function setTime(t) {
  setPlaying(false);
  state.t = Math.min(Math.max(Number(t), time[0]), time[T - 1]);
  showIndex(nearestIndex(state.t));
  renderNow();
  return time[state.k];
}

function chartTime(ev) {
  const r = chart.getBoundingClientRect();
  const f = (ev.clientX - r.left - PAD.left) / (r.width - PAD.left - PAD.right);
  return time[0] + Math.min(Math.max(f, 0), 1) * (time[T - 1] - time[0]);
}

function wireControls() {
  $('nm-play').addEventListener('click', () => {
    if (!state.playing && state.k === T - 1) state.t = time[0];
    setPlaying(!state.playing);
  });
  $('nm-speed').addEventListener('change', (e) => { state.speed = Number(e.target.value); });
  slider.addEventListener('input', () => { setPlaying(false); state.t = time[+slider.value]; showIndex(+slider.value); requestRender(); });
  for (const name of Object.keys(layers)) {
    const box = $('nm-layer-' + name);
    box.addEventListener('change', () => { layers[name].visible = box.checked; requestRender(); });
    const sw = $('nm-sw-' + name), col = { character: COLORS.perturbed, ghost: COLORS.ghost, forces: COLORS.force, ball: COLORS.ball }[name];
    if (sw && col) sw.style.background = '#' + rgb(col).getHexString();
  }
  // Space: play/pause; arrow keys: one sample back or on.
  document.addEventListener('keydown', (e) => {
    if (e.target.closest && e.target.closest('select, input, button')) return;   // their own keys
    if (e.key === ' ') { e.preventDefault(); $('nm-play').click(); }
    if (e.key === 'ArrowLeft' || e.key === 'ArrowRight') {
      setTime(time[Math.min(Math.max(state.k + (e.key === 'ArrowLeft' ? -1 : 1), 0), T - 1)]);
    }
  });
  let dragging = false;
  chart.addEventListener('pointerdown', (e) => { dragging = true; chart.setPointerCapture(e.pointerId); setTime(chartTime(e)); });
  chart.addEventListener('pointermove', (e) => { if (dragging) setTime(chartTime(e)); });
  chart.addEventListener('pointerup', () => { dragging = false; });
  controls.addEventListener('change', requestRender);
  // Redrawn at once (not on the next animation frame): a resized canvas is blank until drawn.
  new ResizeObserver(() => { drawChart(Math.max(state.k, 0)); renderNow(); }).observe($('nm-view'));
}

function describe() {
  const m = D.meta.metrics || {};
  const bits = [];
  const num = (x) => typeof x === 'number' && isFinite(x);
  if (num(m.peak_deviation_deg)) bits.push('peak ' + m.peak_deviation_deg.toFixed(2) + ' deg' + (num(m.time_of_peak_s) ? ' at ' + m.time_of_peak_s.toFixed(2) + ' s' : ''));
  if (num(m.recovery_time_s)) bits.push('recovery ' + m.recovery_time_s.toFixed(2) + ' s');
  if (F.label) bits.push('hit ' + F.label);
  if (num(m.assist_impulse_Ns)) bits.push('assist (not physics, purple arrow) ' + m.assist_impulse_Ns.toFixed(1) + ' N s' + (num(m.assist_impulse_pct) ? ' = ' + m.assist_impulse_pct.toFixed(2) + ' % BW' : ''));
  $('nm-metrics').textContent = bits.join(' \u00b7 ');
}

// The page's state for tests and scripts: the sample shown, and whether anything was fetched.
function reportReady() {
  const fetched = performance.getEntriesByType('resource').map((e) => e.name).filter((u) => /^https?:/i.test(u));
  if (fetched.length) window.neuromotorReport('fetched from the network: ' + fetched.join(' '));
  const status = $('nm-status');
  status.textContent = 'ready';
  status.setAttribute('data-webgl', renderer && renderer.getContext() ? '1' : '0');
  document.documentElement.setAttribute('data-nm-ready', '1');
}

window.neuromotorSetTime = setTime;
wireControls();
describe();
// ?t=SECONDS: that instant, paused; else play from the start. ?speed=0.5 (1, 0.5, 0.25, 0.1).
const query = new URLSearchParams(window.location.search);
const t0 = query.has('t') ? Number(query.get('t')) : NaN;
const speedBox = $('nm-speed');
if ([...speedBox.options].some((o) => Number(o.value) === Number(query.get('speed')))) {
  speedBox.value = String(Number(query.get('speed')));
  state.speed = Number(speedBox.value);
}
if (Number.isFinite(t0)) {
  setTime(t0);
} else {
  setTime(time[0]);
  setPlaying(true);
}
reportReady();
