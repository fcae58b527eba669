// 3D preview: the material's glTF export (material.glb) rendered by three.js, on a plane you can
// tilt and on a sphere, lit by the page's light (the same inputs the texture-space view renders).
// Loaded only when config.json offers it (three.js found at export / serve time); three.js comes
// from this site (import map "three" -> three/three.module.js), never from a CDN.
//
// Light units as in torchmetal/formats/parity.py: the base colour is the texture d, so a
// torchmetal light of intensity I is a three.js light of intensity pi*I (candela, decay 2).
// Display as in the texture view: linear * exposure, clipped, sRGB.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const DEG = Math.PI / 180;

export async function createPreview(canvas, cfg) {
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.LinearToneMapping; // = exposure * linear, then clipped by the sRGB output
  renderer.setClearColor(0x2a2e33, 1); // a dim backdrop, so an unlit silhouette still shows
  renderer.setScissorTest(true);

  const gltf = await new GLTFLoader().loadAsync(new URL(cfg.preview.glb, location.href).href);
  let plane = null;
  gltf.scene.traverse((o) => { if (o.isMesh && !plane) plane = o; });
  if (!plane) throw new Error(`${cfg.preview.glb}: expected a mesh, found none`);
  const [sw, sh] = cfg.surface;
  const extent = Math.max(sw, sh);

  // the sphere: same material; uv v flipped to the glTF convention (row 0 at the top) and tangents
  // for the normal map (tangent along +u, as on the exported quad); poles on ±y, row 0 at +y
  const geo = new THREE.SphereGeometry(0.5 * extent, 96, 48);
  const uv = geo.attributes.uv;
  for (let i = 0; i < uv.count; i++) uv.setY(i, 1 - uv.getY(i));
  if (plane.material.normalMap || plane.material.clearcoatNormalMap) geo.computeTangents();
  const sphere = new THREE.Mesh(geo, plane.material);

  const views = [plane, sphere].map((mesh) => {
    const scene = new THREE.Scene();
    const group = new THREE.Group();
    group.add(mesh);
    scene.add(group);
    return { scene, group };
  });
  const point = new THREE.PointLight(0xffffff, 1, 0, 2);
  const dir = new THREE.DirectionalLight(0xffffff, 1);
  // preview camera: looks at the sample from 35° off the normal on the −y side, +y up on screen
  const camera = new THREE.PerspectiveCamera(30, 1, 0.01 * extent, 100 * extent);
  camera.up.set(0, 0, 1);
  const dist = 2.6 * extent;
  camera.position.set(0, -dist * Math.sin(35 * DEG), dist * Math.cos(35 * DEG));
  camera.lookAt(0, 0, 0);

  const tilt = { x: 0, z: 0 };
  let inputs = null, exposure = 1, queued = false;
  const api = { frames: 0, tilt, error: null };

  function applyTilt() {
    for (const v of views) v.group.rotation.set(tilt.x * DEG, 0, tilt.z * DEG, "ZXY");
  }

  function draw() {
    queued = false;
    if (!inputs) return;
    const [x, y, z, w] = inputs.light;
    const I = inputs.light_intensity;
    const top = Math.max(...I, 1e-30);
    const light = w > 0.5 ? point : dir;
    light.color.setRGB(I[0] / top, I[1] / top, I[2] / top, THREE.LinearSRGBColorSpace);
    light.intensity = Math.PI * top; // torchmetal I -> three.js pi*I (base colour = d)
    light.position.set(x, y, z);
    renderer.toneMappingExposure = exposure;
    const width = canvas.width, height = canvas.height, half = Math.floor(width / 2);
    camera.aspect = half / height;
    camera.updateProjectionMatrix();
    views.forEach((v, k) => {
      v.scene.add(light); // the light stays in the world frame while the sample tilts
      if (light.isDirectionalLight) v.scene.add(light.target);
      renderer.setViewport(k * half, 0, half, height);
      renderer.setScissor(k * half, 0, half, height);
      renderer.render(v.scene, camera);
    });
    api.frames++;
  }

  api.update = (next, ex) => {
    inputs = next; exposure = ex;
    if (!queued) { queued = true; requestAnimationFrame(draw); }
  };
  api.drawNow = () => draw();

  // pointer drag: horizontal spins the sample about its normal's world axis, vertical tilts it
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    drag = { x: e.clientX, y: e.clientY, tx: tilt.x, tz: tilt.z };
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag || !canvas.hasPointerCapture(e.pointerId)) return;
    tilt.z = drag.tz + (e.clientX - drag.x) * 0.5;
    tilt.x = Math.max(-85, Math.min(85, drag.tx + (e.clientY - drag.y) * 0.5));
    applyTilt();
    api.update(inputs, exposure);
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  applyTilt();
  return api;
}
