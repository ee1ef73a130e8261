// The registration as a 3D statement: the model in the registered pose, the initial pose as a ghost, both
// X-ray sources and detector planes with the views' images on them (the C-arm as it stood), orbit and zoom.
// Coloured by arrival time when hemodynamics were computed (one value per vertex of model.json, same order).
// three.js is vendored (vendor/three/README.md) and loaded only when a job page shows the scene.
"use strict";

const REGISTERED = 0xff6e00;
const GHOST = 0x8a8a8a;
const SOURCE_COLOURS = { ap: 0x2878ff, lat: 0x14a06e };

function matrix(THREE, rows) {
  // a 4x4 row-major (mesh → world) as a three.js Matrix4
  const m = new THREE.Matrix4();
  m.set(...rows[0], ...rows[1], ...rows[2], ...rows[3]);
  return m;
}

function modelGeometry(THREE, model) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(model.vertices, 3));
  geometry.setIndex(model.faces);
  geometry.computeVertexNormals();
  return geometry;
}

// arrival time (s) → RGB along blue (early) → yellow → red (late); null → grey
export function arrivalColours(arrival, low, high) {
  const colours = new Float32Array(arrival.length * 3);
  arrival.forEach((t, i) => {
    let rgb = [0.55, 0.55, 0.55];
    if (t !== null && Number.isFinite(t)) {
      const f = high > low ? Math.min(1, Math.max(0, (t - low) / (high - low))) : 0.5;
      rgb = f < 0.5 ? [f * 2, f * 2, 1 - f * 2] : [1, 1 - (f - 0.5) * 2, 0];
    }
    colours.set(rgb, i * 3);
  });
  return colours;
}

function placed(THREE, geometry, material, pose) {
  const mesh = new THREE.Mesh(geometry, material);
  mesh.matrixAutoUpdate = false;
  mesh.matrix.copy(matrix(THREE, pose));
  return mesh;
}

function detectorPlane(THREE, detector, texture) {
  const c = detector.corners_mm; // top-left, top-right, bottom-right, bottom-left of the stored image
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute([...c[0], ...c[1], ...c[2], ...c[3]], 3));
  geometry.setAttribute("uv", new THREE.Float32BufferAttribute([0, 1, 1, 1, 1, 0, 0, 0], 2)); // flipY: v=1 is the top row
  geometry.setIndex([0, 1, 2, 0, 2, 3]);
  const material = texture ? new THREE.MeshBasicMaterial({ map: texture, side: THREE.DoubleSide })
    : new THREE.MeshBasicMaterial({ color: 0x333333, side: THREE.DoubleSide });
  return new THREE.Mesh(geometry, material);
}

function beamLines(THREE, detector, colour) {
  const s = detector.source_mm;
  const points = detector.corners_mm.flatMap((corner) => [...s, ...corner]);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(points, 3));
  return new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity: 0.45 }));
}

function sourceMarker(THREE, detector, colour) {
  const marker = new THREE.Mesh(new THREE.SphereGeometry(12, 16, 12), new THREE.MeshBasicMaterial({ color: colour }));
  marker.position.set(...detector.source_mm);
  return marker;
}

function frameCamera(THREE, camera, controls, model, registered, whole) {
  // from between the two sources, looking at the model with both detectors behind it (the corner of two
  // "walls" carrying the views); framed on the model and the detectors (`whole`; the sources are farther,
  // off-frame) or on the model alone
  const centre = new THREE.Box3().setFromObject(registered).getCenter(new THREE.Vector3());
  const box = new THREE.Box3().setFromObject(registered);
  if (whole) for (const d of Object.values(model.views)) d.corners_mm.forEach((c) => box.expandByPoint(new THREE.Vector3(...c)));
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const sources = Object.values(model.views).map((d) => new THREE.Vector3(...d.source_mm).sub(centre).normalize());
  const direction = sources.reduce((a, b) => a.add(b), new THREE.Vector3());
  const axis = sources.length === 2 ? new THREE.Vector3().crossVectors(sources[0], sources[1]).normalize() : new THREE.Vector3();
  direction.normalize().addScaledVector(axis, -0.45);
  if (direction.lengthSq() < 1e-6) direction.set(1, 1, 1);
  direction.normalize();
  const distance = (sphere.radius + sphere.center.distanceTo(centre) * 0.5) / Math.tan((camera.fov * Math.PI) / 360);
  camera.position.copy(centre).addScaledVector(direction, distance);
  if (axis.lengthSq() > 0) camera.up.copy(axis).negate();
  camera.near = distance / 100;
  camera.far = distance * 20;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

// Build the scene in `canvas`; `textures`: {view: canvas} (the 2D views as drawn); `arrival`: per vertex or null.
export async function showScene(canvas, model, textures, arrival) {
  const THREE = await import("./vendor/three/three.module.min.js");
  const { OrbitControls } = await import("./vendor/three/OrbitControls.js");
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(canvas.clientWidth, canvas.clientHeight, false);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf4f4f4);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x777777, 2.2), new THREE.AmbientLight(0xffffff, 0.4));
  const geometry = modelGeometry(THREE, model);
  let material = new THREE.MeshLambertMaterial({ color: REGISTERED });
  if (arrival) {
    const known = arrival.filter((t) => t !== null && Number.isFinite(t));
    geometry.setAttribute("color", new THREE.Float32BufferAttribute(
      arrivalColours(arrival, Math.min(...known), Math.max(...known)), 3));
    material = new THREE.MeshLambertMaterial({ vertexColors: true });
  }
  const registered = placed(THREE, geometry, material, model.poses.registered);
  registered.name = "registered";
  const ghost = placed(THREE, geometry, new THREE.MeshBasicMaterial({ color: GHOST, transparent: true, opacity: 0.25,
    depthWrite: false }), model.poses.initial);
  scene.add(registered, ghost);
  const maps = {};
  for (const [name, detector] of Object.entries(model.views)) {
    const texture = textures[name] ? new THREE.CanvasTexture(textures[name]) : null;
    if (texture) { texture.colorSpace = THREE.SRGBColorSpace; maps[name] = texture; }
    const colour = SOURCE_COLOURS[name] || 0x555555;
    scene.add(detectorPlane(THREE, detector, texture), beamLines(THREE, detector, colour), sourceMarker(THREE, detector, colour));
  }
  const camera = new THREE.PerspectiveCamera(35, canvas.clientWidth / canvas.clientHeight, 1, 10000);
  const controls = new OrbitControls(camera, canvas);
  const render = () => { renderer.render(scene, camera); canvas.dataset.frames = String(Number(canvas.dataset.frames || 0) + 1); };
  controls.addEventListener("change", render);
  const frame = (whole) => { frameCamera(THREE, camera, controls, model, registered, whole); render(); };
  frame(true);
  const setTexture = (name, image) => {
    if (!maps[name]) return;
    maps[name].image = image;
    maps[name].needsUpdate = true;
    render();
  };
  return { render, ghost, registered, setTexture, frame };
}
