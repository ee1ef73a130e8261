// The two views as a person reads them: the image registered (frame or frames combined, subtracted) under
// the outlines, each layer a toggle, zoom and pan with both views at one mm scale, the legend in the page.
// Layers come from layers_<view>.png (R: initial outline, G: registered outline, B bit 7: vessel mask,
// B bit 6: unfilled model pixels), decoded once into a pixel mask per layer.
"use strict";

export const LAYERS = [
  { key: "registered", label: "Registered pose (outline)", rgba: [255, 110, 0, 255], on: true, test: (r, g) => g > 127 },
  { key: "initial", label: "Initial pose (outline)", rgba: [40, 120, 255, 255], on: true, test: (r) => r > 127 },
  { key: "unfilled", label: "Unfilled: model with no vessel under it", rgba: [200, 40, 200, 200], on: true, test: (r, g, b) => (b & 64) !== 0 },
  { key: "mask", label: "Segmentation (vessel mask fitted)", rgba: [0, 200, 140, 110], on: false, test: (r, g, b) => (b & 128) !== 0 },
];
const MIN_ZOOM = 0.5;
const MAX_ZOOM = 16;

function decodeLayers(image) {
  // the layers PNG → one RGBA overlay canvas per layer (same grid as the image)
  const w = image.naturalWidth, h = image.naturalHeight;
  const source = Object.assign(document.createElement("canvas"), { width: w, height: h }).getContext("2d");
  source.drawImage(image, 0, 0);
  const pixels = source.getImageData(0, 0, w, h).data;
  return Object.fromEntries(LAYERS.map((layer) => {
    const canvas = Object.assign(document.createElement("canvas"), { width: w, height: h });
    const context = canvas.getContext("2d");
    const out = context.createImageData(w, h);
    for (let i = 0; i < pixels.length; i += 4) {
      if (layer.test(pixels[i], pixels[i + 1], pixels[i + 2])) out.data.set(layer.rgba, i);
    }
    context.putImageData(out, 0, 0);
    return [layer.key, canvas];
  }));
}

function loadImage(url) {
  return new Promise((resolve, reject) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = () => reject(new Error("image not readable"));
    img.src = url;
  });
}

// One shared state: the zoom (both views), which layers show; each view keeps its own pan (in image px).
export function viewsState() {
  return { zoom: 1, shown: Object.fromEntries(LAYERS.map((l) => [l.key, l.on])), views: [], mmPerScreenPx: null };
}

function fitScale(state) {
  // screen px per mm shared by both views: the widest view (in mm) fits its canvas at zoom 1
  const fits = state.views.map((v) => v.canvas.width / (v.width * v.mmPerPx));
  return Math.min(...fits);
}

export function draw(state) {
  const pxPerMm = fitScale(state) * state.zoom;
  for (const v of state.views) {
    const context = v.canvas.getContext("2d");
    const scale = pxPerMm * v.mmPerPx; // screen px per image px
    context.setTransform(1, 0, 0, 1, 0, 0);
    context.fillStyle = "#000000";
    context.fillRect(0, 0, v.canvas.width, v.canvas.height);
    context.imageSmoothingEnabled = state.zoom < 2;
    const left = v.canvas.width / 2 - (v.centre[0] * scale);
    const top = v.canvas.height / 2 - (v.centre[1] * scale);
    context.setTransform(scale, 0, 0, scale, left, top);
    context.drawImage(v.image, 0, 0);
    context.imageSmoothingEnabled = false;
    for (const layer of LAYERS) if (state.shown[layer.key]) context.drawImage(v.layers[layer.key], 0, 0);
    v.canvas.dataset.drawn = String(Number(v.canvas.dataset.drawn || 0) + 1);
  }
  state.onDraw && state.onDraw(pxPerMm);
}

function zoomBy(state, factor) {
  state.zoom = Math.max(MIN_ZOOM, Math.min(MAX_ZOOM, state.zoom * factor));
  draw(state);
}

function attachPanZoom(state, v) {
  let drag = null;
  v.canvas.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY }; v.canvas.setPointerCapture(e.pointerId); });
  v.canvas.addEventListener("pointerup", () => { drag = null; });
  v.canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const scale = fitScale(state) * state.zoom * v.mmPerPx;
    v.centre = [v.centre[0] - (e.clientX - drag.x) / scale, v.centre[1] - (e.clientY - drag.y) / scale];
    drag = { x: e.clientX, y: e.clientY };
    draw(state);
  });
  v.canvas.addEventListener("wheel", (e) => { e.preventDefault(); zoomBy(state, e.deltaY < 0 ? 1.25 : 0.8); }, { passive: false });
  v.canvas.addEventListener("keydown", (e) => {
    const step = 20 / (fitScale(state) * state.zoom * v.mmPerPx);
    const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    if (e.key === "+" || e.key === "=") zoomBy(state, 1.25);
    else if (e.key === "-") zoomBy(state, 0.8);
    else if (moves[e.key]) { v.centre = [v.centre[0] + moves[e.key][0], v.centre[1] + moves[e.key][1]]; draw(state); }
    else return;
    e.preventDefault();
  });
}

// Load one view: the image registered, its layers and its mm per pixel (from model.json's detector).
export async function addView(state, name, canvas, imageUrl, layersUrl, mmPerPx) {
  const [image, layersImage] = await Promise.all([loadImage(imageUrl), loadImage(layersUrl)]);
  const v = { name, canvas, image, layers: decodeLayers(layersImage), width: image.naturalWidth,
    mmPerPx: mmPerPx || 1, centre: [image.naturalWidth / 2, image.naturalHeight / 2] };
  state.views.push(v);
  attachPanZoom(state, v);
  return v;
}

export function resetView(state) {
  state.zoom = 1;
  for (const v of state.views) v.centre = [v.image.naturalWidth / 2, v.image.naturalHeight / 2];
  draw(state);
}

export { zoomBy };

// The view at its own pixel grid with the layers shown now: the texture of its detector in the 3D scene.
export function nativeComposite(state, v) {
  const canvas = Object.assign(document.createElement("canvas"), { width: v.image.naturalWidth, height: v.image.naturalHeight });
  const context = canvas.getContext("2d");
  context.drawImage(v.image, 0, 0);
  for (const layer of LAYERS) if (state.shown[layer.key]) context.drawImage(v.layers[layer.key], 0, 0);
  return canvas;
}
