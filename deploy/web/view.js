// The twin in the browser: splats drawn by Spark (three.js), in the twin's object frame (metres).
//
// Query: camera=N puts the view exactly at training camera N (its intrinsics and pose, OpenCV convention),
// at w x h pixels (default the camera's own size) over a transparent background, with no panel: what the
// browser tests compare with the engine's render. layers=splats,mesh,cad,cameras,heatmap picks the layers
// shown first (default splats). splats=FILE draws another splat file of the twin's folder (an export: .spz, .ply),
// with frame=16 numbers (row-major [4, 4]) taking its coordinates to the object frame (an export stood +Y up).
// When everything asked for is drawn, window.cadsplatReady is true.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

// The root node mesh_*.glb carry to stand the object frame upright in +Y-up viewers (reconstruction/mesh_io.py):
// undone here, so every layer lies in the object frame the splats and cameras are in.
const OBJECT_FRAME_NODE = "cadsplat_object_z_up";
// Frames drawn after the splats load before the view counts as settled: Spark sorts them on a worker.
const SETTLE_FRAMES = 12;

const params = new URLSearchParams(location.search);
const statusLine = document.getElementById("status");
const say = (text) => { statusLine.textContent = text; };

async function getJson(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: ${r.status} ${r.statusText}`);
  return r.json();
}

async function exists(url) {
  const r = await fetch(url);
  return r.ok;
}

// OpenGL projection of pinhole K for a w x h image, pixel coordinates as OpenCV's (0 at the image's left edge).
function projectionFromK(K, w, h, near, far) {
  const [fx, cx, fy, cy] = [K[0][0], K[0][2], K[1][1], K[1][2]];
  return new THREE.Matrix4().set(
    2 * fx / w, 0, 1 - 2 * cx / w, 0,
    0, 2 * fy / h, 2 * cy / h - 1, 0,
    0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
    0, 0, -1, 0);
}

// Camera-to-object pose, OpenCV axes (x right, y down, z forward) turned into three's (y up, looking down -z).
function c2wOpenGL(c2w) {
  return new THREE.Matrix4().set(...c2w.flat()).multiply(new THREE.Matrix4().makeScale(1, -1, -1));
}

function placeCamera(camera, cam) {
  c2wOpenGL(cam.c2w_object_opencv).decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
}

// Lines from the camera centre to its image corners at `depth` metres, in the object frame.
function frustum(cam, depth) {
  const K = cam.K, c2w = new THREE.Matrix4().set(...cam.c2w_object_opencv.flat());
  const corner = (u, v) => new THREE.Vector3((u - K[0][2]) / K[0][0] * depth, (v - K[1][2]) / K[1][1] * depth, depth).applyMatrix4(c2w);
  const o = new THREE.Vector3().applyMatrix4(c2w);
  const c = [corner(0, 0), corner(cam.width, 0), corner(cam.width, cam.height), corner(0, cam.height)];
  const pts = [];
  for (let i = 0; i < 4; i++) pts.push(o, c[i], c[i], c[(i + 1) % 4]);
  pts.push(c[0].clone().lerp(c[1], 0.4), c[0].clone().lerp(c[1], 0.5).add(c[0].clone().sub(c[3]).multiplyScalar(0.15)));
  pts.push(c[0].clone().lerp(c[1], 0.5).add(c[0].clone().sub(c[3]).multiplyScalar(0.15)), c[0].clone().lerp(c[1], 0.6));
  return pts;
}

async function loadGlb(url) {
  const gltf = await new GLTFLoader().loadAsync(url);
  const scene = gltf.scene;
  scene.updateMatrixWorld(true);
  const root = scene.getObjectByName(OBJECT_FRAME_NODE);
  if (root) {
    scene.applyMatrix4(root.matrixWorld.clone().invert());
    scene.updateMatrixWorld(true);
  }
  return scene;
}

function meshesOf(object) {
  const out = [];
  object.traverse((o) => { if (o.isMesh) out.push(o); });
  return out;
}

// The heat map's colours are the legend's sRGB values (written as COLOR_0 bytes by `cadsplat inspect`); three
// reads COLOR_0 as linear and encodes to sRGB on output, so they are decoded once here to come out as written.
function heatMap(scene) {
  const color = new THREE.Color();
  for (const mesh of meshesOf(scene)) {
    const src = mesh.geometry.getAttribute("color");
    if (src) {
      const lin = new Float32Array(src.count * 3);
      for (let i = 0; i < src.count; i++) {
        color.setRGB(src.getX(i), src.getY(i), src.getZ(i), THREE.SRGBColorSpace);
        lin.set([color.r, color.g, color.b], 3 * i);
      }
      mesh.geometry.setAttribute("color", new THREE.BufferAttribute(lin, 3));
    }
    mesh.material = new THREE.MeshBasicMaterial({ vertexColors: Boolean(src), side: THREE.DoubleSide });
  }
  return scene;
}

function outline(scene) {
  const group = new THREE.Group();
  const material = new THREE.LineBasicMaterial({ color: 0x1f3a93 });
  for (const mesh of meshesOf(scene)) {
    const lines = new THREE.LineSegments(new THREE.EdgesGeometry(mesh.geometry, 25), material);
    lines.applyMatrix4(mesh.matrixWorld);
    group.add(lines);
  }
  return group;
}

function greyMesh(scene) {
  for (const mesh of meshesOf(scene)) {
    mesh.material = new THREE.MeshStandardMaterial({ color: 0xb8b8b8, roughness: 0.7, metalness: 0.0, side: THREE.DoubleSide });
  }
  return scene;
}

async function main() {
  const twin = await getJson("/twin/twin.json");
  const cameras = twin.cameras;
  const exactIndex = params.has("camera") ? Number(params.get("camera")) : null;
  if (exactIndex !== null && !(Number.isInteger(exactIndex) && exactIndex >= 0 && exactIndex < cameras.length)) {
    throw new Error(`camera=${params.get("camera")}: the twin has cameras 0..${cameras.length - 1}`);
  }
  const wanted = new Set((params.get("layers") ?? "splats").split(",").filter(Boolean));

  // Distances in the object frame set the clip planes and the frusta's size.
  const distances = cameras.map((c) => Math.hypot(c.c2w_object_opencv[0][3], c.c2w_object_opencv[1][3], c.c2w_object_opencv[2][3]));
  const reach = distances.length ? distances.reduce((a, b) => a + b) / distances.length : 1.0;
  const near = reach / 100, far = reach * 100;

  const canvas = document.getElementById("view");
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, alpha: true, preserveDrawingBuffer: true });
  renderer.setClearColor(0x000000, 0);
  const scene = new THREE.Scene();
  scene.add(new THREE.HemisphereLight(0xffffff, 0x808080, 1.6), new THREE.AmbientLight(0xffffff, 0.4));
  const spark = new SparkRenderer({ renderer, preBlurAmount: twin.eps2d ?? 0.3, blurAmount: 0, maxStdDev: 3, minAlpha: 1 / 255,
                                    sortRadial: false });
  scene.add(spark);

  const camera = new THREE.PerspectiveCamera(50, 1, near, far);
  let controls = null;
  if (exactIndex !== null) {
    document.body.classList.add("exact");
    const cam = cameras[exactIndex];
    const w = Number(params.get("w") ?? cam.width), h = Number(params.get("h") ?? cam.height);
    const sx = w / cam.width, sy = h / cam.height;
    const K = [[cam.K[0][0] * sx, 0, cam.K[0][2] * sx], [0, cam.K[1][1] * sy, cam.K[1][2] * sy], [0, 0, 1]];
    renderer.setPixelRatio(1);
    renderer.setSize(w, h);
    placeCamera(camera, cam);
    camera.projectionMatrix.copy(projectionFromK(K, w, h, near, far));
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  } else {
    renderer.setPixelRatio(window.devicePixelRatio);
    controls = new OrbitControls(camera, canvas);
    const fit = () => {
      renderer.setSize(window.innerWidth, window.innerHeight);
      camera.aspect = window.innerWidth / window.innerHeight;
      camera.updateProjectionMatrix();
    };
    window.addEventListener("resize", fit);
    fit();
    const select = document.getElementById("camera");
    cameras.forEach((c, i) => select.add(new Option(`${i}: ${c.camera_id}`, String(i))));
    const goTo = (cam) => {
      camera.fov = THREE.MathUtils.radToDeg(2 * Math.atan(cam.height / (2 * cam.K[1][1])));
      camera.updateProjectionMatrix();
      placeCamera(camera, cam);
      camera.up.set(0, 1, 0).applyQuaternion(camera.quaternion);
      const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(camera.quaternion);
      controls.target.copy(camera.position).addScaledVector(forward, camera.position.length());
      controls.update();
    };
    select.addEventListener("change", () => { if (select.value !== "") goTo(cameras[Number(select.value)]); });
    if (cameras.length) {
      select.value = "0";
      goTo(cameras[0]);
    }
  }

  // Layers: each loads when first shown; a missing file greys its toggle out.
  const layers = {
    splats: async () => {
      const mesh = new SplatMesh({ url: splatsUrl, extSplats: true });
      await mesh.initialized;
      if (params.has("frame")) {
        const m = params.get("frame").split(",").map(Number);
        if (m.length !== 16 || m.some((x) => !Number.isFinite(x))) throw new Error("frame= needs 16 numbers, a row-major [4, 4]");
        mesh.applyMatrix4(new THREE.Matrix4().set(...m));
      }
      return mesh;
    },
    mesh: async () => greyMesh(await loadGlb("/twin/mesh_deformed.glb")),
    cad: async () => outline(await loadGlb("/twin/mesh_cad.glb")),
    cameras: async () => {
      const pts = cameras.flatMap((c) => frustum(c, 0.2 * reach));
      return new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(pts), new THREE.LineBasicMaterial({ color: 0xd35400 }));
    },
    heatmap: async () => heatMap(await loadGlb("/inspection/deviation.glb")),
  };
  const splatsUrl = `/twin/${params.get("splats") ?? "splats.ply"}`;
  const sources = { splats: splatsUrl, mesh: "/twin/mesh_deformed.glb", cad: "/twin/mesh_cad.glb", heatmap: "/inspection/deviation.glb" };
  const loaded = {};
  const show = async (name, on) => {
    if (on && !loaded[name]) {
      say(`loading ${name}…`);
      loaded[name] = await layers[name]();
      scene.add(loaded[name]);
    }
    if (loaded[name]) loaded[name].visible = on;
    if (name === "heatmap") document.getElementById("legend").hidden = !on;
  };

  const inspection = await fetch("/inspection/inspection.json").then((r) => (r.ok ? r.json() : null));
  if (inspection) {
    const v = inspection.verdict;
    const verdict = document.getElementById("verdict");
    verdict.textContent = v.line;
    verdict.className = v.status;
    const legend = document.getElementById("legend");
    legend.src = "/inspection/legend.png";
  }
  for (const box of document.querySelectorAll("input[data-layer]")) {
    const name = box.dataset.layer;
    const source = sources[name];
    if (source && !(await exists(source))) {
      box.disabled = true;
      box.parentElement.classList.add("absent");
      box.parentElement.title = `${source} is not in this twin`;
      continue;
    }
    box.checked = wanted.has(name);
    box.addEventListener("change", () => show(name, box.checked).catch(fail));
  }
  for (const name of wanted) {
    if (!(name in layers)) throw new Error(`layers=${name}: not one of ${Object.keys(layers).join(", ")}`);
    await show(name, true);
  }

  let frames = 0;
  renderer.setAnimationLoop(() => {
    controls?.update();
    renderer.render(scene, camera);
    if (++frames === SETTLE_FRAMES) {
      say(`${twin.model_id}: ${twin.num_splats} splats, ${cameras.length} training cameras`);
      window.cadsplatReady = true;
    }
  });
}

function fail(error) {
  say(`error: ${error.message}`);
  window.cadsplatError = String(error.message);
}

main().catch(fail);
