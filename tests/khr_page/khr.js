// The browser tests' second third-party reader: Babylon.js's glTF loader reads the KHR_gaussian_splatting GLB
// (/twin/splats.glb, +Y up) and draws it from training camera ?camera=N of /twin/twin.json, the GLB's frame
// given by ?frame= (row-major [4, 4] glTF-from-object). Sets window.cadsplatReady once drawn.
// ?kernel=K sets Babylon's kernelSize (default: the one that draws the GLB's eps2d, below; window.cadsplatKernelSize
// says which it used); ?background=white clears to opaque white, so that Babylon composites the splats over white
// itself (default: transparent).
"use strict";

// The dilation the splats were fitted with: the GLB's root extras.cadsplat.eps2d (simulation/export.py), else twin.json's.
function eps2dOf(result, twin) {
  for (const node of result.transformNodes.concat(result.meshes)) {
    const eps2d = node.metadata?.gltf?.extras?.cadsplat?.eps2d;
    if (typeof eps2d === "number") return eps2d;
  }
  return twin.eps2d ?? 0.3;
}

async function main() {
  const params = new URLSearchParams(location.search);
  const twin = await (await fetch("/twin/twin.json")).json();
  const cam = twin.cameras[Number(params.get("camera"))];
  const T = params.get("frame").split(",").map(Number);
  const [w, h] = [cam.width, cam.height];
  const canvas = document.getElementById("view");
  canvas.width = w; canvas.height = h;
  canvas.style.width = `${w}px`; canvas.style.height = `${h}px`;
  const engine = new BABYLON.Engine(canvas, false, { preserveDrawingBuffer: true, premultipliedAlpha: true, alpha: true }, false);
  engine.setHardwareScalingLevel(1);
  const scene = new BABYLON.Scene(engine);
  scene.useRightHandedSystem = true;
  scene.clearColor = params.get("background") === "white" ? new BABYLON.Color4(1, 1, 1, 1) : new BABYLON.Color4(0, 0, 0, 0);

  // Camera-to-glTF pose: T times the OpenCV camera-to-object pose; OpenCV looks down +z with y down.
  const M = (a) => (r, c) => a[4 * r + c];
  const t = M(T), c2w = (r, c) => cam.c2w_object_opencv[r][c];
  const mul = (r, c) => [0, 1, 2, 3].reduce((s, k) => s + t(r, k) * c2w(k, c), 0);
  const col = (c) => new BABYLON.Vector3(mul(0, c), mul(1, c), mul(2, c));
  const eye = col(3), forward = col(2), down = col(1);
  // The orientation as a quaternion (Babylon's camera looks down its local -z in a right-handed scene), not a target:
  // a camera aimed by setTarget keeps only yaw and pitch, and misses the roll by a fraction of a degree (half a pixel).
  const camera = new BABYLON.TargetCamera("training", eye, scene);
  const up = down.scale(-1);
  camera.updateUpVectorFromRotation = true;
  const back = forward.scale(-1);
  camera.rotationQuaternion = BABYLON.Quaternion.RotationQuaternionFromAxis(BABYLON.Vector3.Cross(up, back), up, back);
  const [fx, cx, fy, cy] = [cam.K[0][0], cam.K[0][2], cam.K[1][1], cam.K[1][2]];
  const reach = Math.hypot(eye.x, eye.y, eye.z), near = reach / 100, far = reach * 100;
  // OpenGL's projection of K, stored as Babylon stores matrices (row vectors: the transpose, row-major).
  const P = [2 * fx / w, 0, 0, 0,
             0, 2 * fy / h, 0, 0,
             1 - 2 * cx / w, 2 * cy / h - 1, -(far + near) / (far - near), -1,
             0, 0, -2 * far * near / (far - near), 0];
  camera.minZ = near; camera.maxZ = far;
  camera.freezeProjectionMatrix(BABYLON.Matrix.FromArray(P));

  const result = await BABYLON.ImportMeshAsync("/twin/splats.glb", scene);
  // Babylon adds kernelSize to four times the splat's screen covariance (it builds the covariance from twice the
  // scales, gaussianSplattingMeshBase.pure.ts _makeSplat, and draws its quad at invViewport = 1 / width), so the
  // variance it dilates by is kernelSize / 4: 4 eps2d dilates by the engine's eps2d.
  const kernel = params.has("kernel") ? Number(params.get("kernel")) : 4 * eps2dOf(result, twin);
  for (const mesh of result.meshes) {
    if (mesh.material && "kernelSize" in mesh.material) mesh.material.kernelSize = kernel;
  }
  window.cadsplatKernelSize = kernel;
  let frames = 0;
  engine.runRenderLoop(() => {
    scene.render();
    if (++frames === 30) window.cadsplatReady = true;
  });
}

main().catch((e) => { window.cadsplatError = String(e && e.message || e); });
