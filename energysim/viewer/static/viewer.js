// The energysim viewer page: draws the trajectory served at /trajectory.bin and loops over it,
// polling /version so that a new trajectory from Python replaces the old one without a reload.
// Message format: see energysim/viewer/trajectory.py.
import * as THREE from './three.bundle.min.js';
import { OrbitControls } from './three.bundle.min.js';

const POLL_MS = 250;
const BODY_COLOR = '#8fb3d9';
// Viridis at five stops; the page interpolates between them.
const RAMP = ['#440154', '#3b528b', '#21918c', '#5ec962', '#fde725'];

const el = (id) => document.getElementById(id);
const view = el('view');
const statusLine = el('status');
const playButton = el('play');
const slider = el('slider');
const timeLabel = el('time');
const fieldSelect = el('field');
const legend = el('legend');

const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(window.devicePixelRatio);
view.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.background = new THREE.Color('#eef1f5');
const camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
// A light that moves with the camera keeps the lit side facing the viewer while orbiting.
const headlight = new THREE.DirectionalLight(0xffffff, 1.6);
headlight.position.set(0.5, 1, 0.3);
camera.add(headlight);
scene.add(camera, new THREE.HemisphereLight(0xffffff, 0x9a9a9a, 1.6));
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
// Draw only when something changed: software GL (no GPU) would otherwise keep a CPU core busy.
controls.addEventListener('change', () => { state.needsRender = true; });

const geometry = new THREE.BufferGeometry();
const body = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({
  vertexColors: true, flatShading: true, roughness: 0.75, metalness: 0, side: THREE.DoubleSide,
  polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1,
}));
const wire = new THREE.Mesh(geometry, new THREE.MeshBasicMaterial({
  color: 0x1b1b1b, wireframe: true, transparent: true, opacity: 0.3,
}));
const ground = new THREE.Group();
const markers = new THREE.Group();
scene.add(body, wire, ground, markers);

// Colours are given in sRGB; three.js wants vertex colours in linear space.
const rampLinear = RAMP.map((c) => new THREE.Color(c));
const bodyLinear = new THREE.Color(BODY_COLOR);

const state = {
  data: null, loadedVersion: 0, loadedSession: '', loading: false, playing: true, time: 0, frame: -1,
  field: '', dirty: true, fitted: false, groundHeight: undefined, needsRender: true, lastTick: performance.now(),
};
// For tests and the curious: what the page shows, and where a world point lands on the canvas.
window.__viewer = {
  session: '', version: 0, renderedVersion: 0, framesDrawn: 0, frame: 0, numFrames: 0, error: null,
  project(x, y, z) {
    const v = new THREE.Vector3(x, y, z).project(camera);
    const { clientWidth: w, clientHeight: h } = renderer.domElement;
    return [(v.x + 1) / 2 * w, (1 - v.y) / 2 * h];
  },
  setPlaying(on) { setPlaying(on); },
  setField(name) { fieldSelect.value = name; selectField(); return state.field === name; },
};

function parse(buffer) {
  const magic = new TextDecoder().decode(new Uint8Array(buffer, 0, 4));
  if (magic !== 'ESV1') throw new Error(`unexpected trajectory format ${JSON.stringify(magic)}`);
  const headerLength = new DataView(buffer).getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 8, headerLength)));
  const base = 8 + headerLength;
  const arrays = {};
  for (const [name, b] of Object.entries(header.buffers)) {
    const count = b.shape.reduce((a, c) => a * c, 1);
    const Type = b.dtype === 'uint32' ? Uint32Array : Float32Array;
    arrays[name] = new Type(buffer, base + b.offset, count);
  }
  return { header, arrays };
}

function install(data) {
  const { header, arrays } = data;
  const corners = header.num_faces * 3;
  if (!geometry.getAttribute('position') || geometry.getAttribute('position').count !== corners) {
    geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(corners * 3), 3));
    geometry.setAttribute('color', new THREE.BufferAttribute(new Float32Array(corners * 3), 3));
  }
  data.bounds = trajectoryBounds(arrays.positions, header.markers);
  state.data = data;
  state.loadedVersion = header.version;
  state.loadedSession = header.session;
  window.__viewer.version = header.version;
  window.__viewer.session = header.session;
  window.__viewer.numFrames = header.num_frames;
  slider.max = String(header.num_frames - 1);

  const names = header.fields.map((f) => f.name);
  fieldSelect.replaceChildren(new Option('plain', ''), ...names.map((n) => new Option(n, n)));
  if (!names.includes(state.field)) state.field = '';
  fieldSelect.value = state.field;

  buildMarkers(header.markers);
  // The camera and the ground stay put when a trajectory is replaced, so motion between versions shows.
  if (!state.fitted) fitView();
  if (header.ground_height !== state.groundHeight) buildGround(header.ground_height);
  state.frame = -1;
  state.dirty = true;
}

function trajectoryBounds(positions, markerList) {
  const box = new THREE.Box3();
  const p = new THREE.Vector3();
  for (let i = 0; i < positions.length; i += 3) box.expandByPoint(p.set(positions[i], positions[i + 1], positions[i + 2]));
  for (const m of markerList) {
    const half = m.shape === 'sphere' ? new THREE.Vector3().setScalar(m.size[0]) : new THREE.Vector3(...m.size).multiplyScalar(0.5);
    const c = new THREE.Vector3(...m.position);
    box.expandByPoint(c.clone().sub(half)).expandByPoint(c.add(half));
  }
  return box;
}

function fitView() {
  const { bounds, header } = state.data;
  const center = bounds.getCenter(new THREE.Vector3());
  const radius = Math.max(bounds.getSize(new THREE.Vector3()).length() / 2, 1e-3);
  const distance = 1.25 * radius / Math.sin(THREE.MathUtils.degToRad(camera.fov) / 2);
  const direction = header.dim === 2 ? new THREE.Vector3(0, 0.15, 1) : new THREE.Vector3(0.55, 0.45, 1.0);
  camera.position.copy(center).addScaledVector(direction.normalize(), distance);
  camera.near = distance / 100;
  camera.far = distance * 100;
  camera.updateProjectionMatrix();
  controls.target.copy(center);
  controls.update();
  state.fitted = true;
  state.extent = radius;
}

function buildGround(height) {
  ground.clear();
  state.groundHeight = height;
  if (height === null || height === undefined) return;
  const { bounds } = state.data;
  const center = bounds.getCenter(new THREE.Vector3());
  const size = 8 * Math.max(state.extent, 0.25);
  const plane = new THREE.Mesh(new THREE.PlaneGeometry(size, size),
    // Slightly see-through: scenes without contact may pass below it, and should stay visible there.
    new THREE.MeshStandardMaterial({ color: '#d9d4c7', roughness: 1, transparent: true, opacity: 0.85,
      depthWrite: false, polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1 }));
  plane.rotation.x = -Math.PI / 2;
  const grid = new THREE.GridHelper(size, 16, 0xa39c8a, 0xbdb6a4);
  for (const part of [plane, grid]) part.position.set(center.x, height, center.z);
  ground.add(plane, grid);
}

function buildMarkers(list) {
  markers.clear();
  for (const m of list) {
    const shape = m.shape === 'sphere' ? new THREE.SphereGeometry(m.size[0], 32, 16) : new THREE.BoxGeometry(...m.size);
    const mesh = new THREE.Mesh(shape, new THREE.MeshStandardMaterial({ color: m.color, roughness: 0.5 }));
    mesh.position.set(...m.position);
    mesh.name = m.name;
    markers.add(mesh);
  }
}

function rampColor(t, out) {
  const x = Math.min(Math.max(t, 0), 1) * (rampLinear.length - 1);
  const i = Math.min(Math.floor(x), rampLinear.length - 2);
  return out.copy(rampLinear[i]).lerp(rampLinear[i + 1], x - i);
}

function drawFrame(frame) {
  const { header, arrays } = state.data;
  const k = header.num_points;
  const s = header.num_faces;
  const faces = arrays.faces;
  const points = arrays.positions.subarray(frame * k * 3, (frame + 1) * k * 3);
  const position = geometry.getAttribute('position');
  const color = geometry.getAttribute('color');
  for (let c = 0; c < 3 * s; c++) {
    const v = faces[c] * 3;
    position.array[3 * c] = points[v];
    position.array[3 * c + 1] = points[v + 1];
    position.array[3 * c + 2] = points[v + 2];
  }
  const field = header.fields.find((f) => f.name === state.field);
  const tmp = new THREE.Color();
  if (field) {
    const values = arrays[`field:${field.name}`];
    const span = field.max > field.min ? field.max - field.min : 1;
    const perFace = field.location === 'face';
    const row = frame * (perFace ? s : k);
    for (let c = 0; c < 3 * s; c++) {
      const value = values[row + (perFace ? Math.floor(c / 3) : faces[c])];
      rampColor((value - field.min) / span, tmp).toArray(color.array, 3 * c);
    }
  } else {
    for (let c = 0; c < 3 * s; c++) bodyLinear.toArray(color.array, 3 * c);
  }
  position.needsUpdate = true;
  color.needsUpdate = true;
  geometry.computeVertexNormals();
  geometry.computeBoundingSphere();
  updateLegend(field);
}

function updateLegend(field) {
  legend.style.display = field ? 'block' : 'none';
  if (!field) return;
  legend.querySelector('.name').textContent = field.name;
  legend.querySelector('.ramp').style.background = `linear-gradient(to right, ${RAMP.join(', ')})`;
  legend.querySelector('.low').textContent = field.min.toPrecision(3);
  legend.querySelector('.high').textContent = field.max.toPrecision(3);
}

function setPlaying(on) {
  state.playing = on;
  playButton.textContent = on ? 'pause' : 'play';
}

function selectField() {
  // An unknown name (assigned from script) leaves the select empty: fall back to plain.
  if (fieldSelect.selectedIndex < 0) fieldSelect.value = '';
  state.field = fieldSelect.value;
  state.dirty = true;
}

function resize() {
  const w = view.clientWidth;
  const h = view.clientHeight;
  renderer.setSize(w, h);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  state.needsRender = true;
}

function tick(now) {
  const elapsed = Math.min((now - state.lastTick) / 1000, 0.25);
  state.lastTick = now;
  if (state.data) {
    const { header } = state.data;
    if (state.playing) state.time += elapsed;
    const frame = Math.floor(state.time / header.frame_dt) % header.num_frames;
    if (frame !== state.frame || state.dirty) {
      drawFrame(frame);
      state.frame = frame;
      state.dirty = false;
      state.needsRender = true;
      slider.value = String(frame);
      timeLabel.textContent = `frame ${frame + 1}/${header.num_frames}, t = ${(frame * header.frame_dt).toFixed(3)} s`;
    }
  }
  controls.update();
  if (state.needsRender) {
    renderer.render(scene, camera);
    state.needsRender = false;
    if (state.data) {
      window.__viewer.framesDrawn += 1;
      window.__viewer.frame = state.frame;
      window.__viewer.renderedVersion = state.loadedVersion;
    }
  }
  requestAnimationFrame(tick);
}

async function load() {
  state.loading = true;
  try {
    const response = await fetch('trajectory.bin', { cache: 'no-store' });
    if (!response.ok) throw new Error(`trajectory: HTTP ${response.status}`);
    install(parse(await response.arrayBuffer()));
    const { header } = state.data;
    showStatus(`version ${header.version}: ${header.num_frames} frames, ${header.num_faces} faces`);
  } finally {
    state.loading = false;
  }
}

function showStatus(text, error = false) {
  statusLine.textContent = text;
  statusLine.className = error ? 'error' : '';
  window.__viewer.error = error ? text : null;
}

async function poll() {
  try {
    if (!state.loading) {
      const response = await fetch('version', { cache: 'no-store' });
      const { session, version } = await response.json();
      if (version !== state.loadedVersion || session !== state.loadedSession) await load();
      else if (window.__viewer.error) showStatus(`version ${version}`);
    }
  } catch (err) {
    // The server may be stopped or restarting: keep the last trajectory and try again.
    showStatus(`no connection to the server (${err.message}); retrying`, true);
  }
  setTimeout(poll, POLL_MS);
}

playButton.addEventListener('click', () => setPlaying(!state.playing));
slider.addEventListener('input', () => {
  if (!state.data) return;
  state.time = Number(slider.value) * state.data.header.frame_dt;
  state.dirty = true;
});
fieldSelect.addEventListener('change', selectField);
el('reset').addEventListener('click', () => { if (state.data) { fitView(); buildGround(state.data.header.ground_height); } });
window.addEventListener('keydown', (event) => {
  if (event.code === 'Space' && !['SELECT', 'BUTTON'].includes(event.target.tagName)) { setPlaying(!state.playing); event.preventDefault(); }
});
window.addEventListener('resize', resize);
resize();
requestAnimationFrame(tick);
poll();
