"""`cadsplat view`: the server serves the twin's own files only, on loopback unless told (then with a token), and stops
cleanly; in headless Chromium the page draws the splats as the engine renders them, and the inspection's colours."""

import http.client
import os
import signal
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from calibration.camera import look_at_c2w
from calibration.sim3 import Sim3
from deploy.view import VENDOR_DIR, ViewRoots, ViewServer, resolve_url_path
from reconstruction.gaussians import Gaussians, render
from reconstruction.mesh_io import MeshParts
from reconstruction.splats import SH_C0, init_splats
from reconstruction.twin import Twin, TwinCamera, save_twin
from tests.browser import Chromium, chromium_binary, iou, psnr_over

SPARK = VENDOR_DIR / "@sparkjsdev/spark/dist/spark.module.js"
needs_vendor = pytest.mark.skipif(not SPARK.is_file(), reason=f"three.js and Spark are not vendored ({VENDOR_DIR}): run `make env`")
needs_chromium = pytest.mark.skipif(chromium_binary() is None, reason="no chromium on the PATH (`make env` installs Debian's where apt is)")


def ball_and_block(dent_m: float = 0.0) -> MeshParts:
    """A ball (radius 40 mm) and a block beside it, metres; `dent_m` pushes the ball's +x cap in by up to that much."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.04)
    block = trimesh.creation.box(extents=[0.03, 0.02, 0.06]).apply_translation([0.06, 0.0, 0.01])
    v = np.concatenate([ball.vertices, block.vertices])
    if dent_m:
        nb = len(ball.vertices)
        push = dent_m * np.clip((v[:nb, 0] / 0.04 - 0.6) / 0.4, 0, 1)
        v[:nb] -= push[:, None] * v[:nb] / 0.04
    f = np.concatenate([ball.faces, block.faces + len(ball.vertices)])
    part = np.concatenate([np.zeros(len(ball.faces), np.int64), np.ones(len(block.faces), np.int64)])
    return MeshParts(v, f, part, ["ball", "block"])


def painted_gaussians(parts: MeshParts, n: int, seed: int = 0):
    """Splats on `parts` that make every convention visible: a random colour each, anisotropic scales in random
    orientations, opacities across the range, SH degree 3 with all bands non-zero."""
    rng = np.random.default_rng(seed)
    s = init_splats(parts.vertices, parts.faces, n, sh_degree=3, face_part=parts.face_part, seed=seed)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = (rng.uniform(0.1, 0.9, (n, 3)) - 0.5) / SH_C0
    sh[:, 1:4] = rng.normal(0, 0.25, (n, 3, 3))
    sh[:, 4:] = rng.normal(0, 0.08, (n, 12, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    disk = np.exp(np.asarray(s.gaussians.log_scales)).mean(1, keepdims=True)
    log_scales = np.log(disk * np.exp(rng.uniform(-1.6, 0.9, (n, 3))))
    g = Gaussians.from_arrays(s.means, quats, log_scales, rng.uniform(-1.0, 3.0, n), sh)
    return g, s


def make_twin(path, dent_m: float = 0.0):
    parts = ball_and_block()
    g, s = painted_gaussians(parts, 6000)
    K = np.array([[300.0, 0, 165], [0, 300.0, 118], [0, 0, 1]])
    centre = np.array([0.02, 0.0, 0.0])
    cams = []
    for el in np.radians([-30.0, 40.0]):
        for az in np.linspace(0, 2 * np.pi, 4, endpoint=False):
            eye = centre + 0.35 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            cams.append(TwinCamera(f"images/c{len(cams):02d}.png", f"c{len(cams):02d}", K, 320, 240, look_at_c2w(eye, centre)))
    twin = Twin(
        model_id="ball_and_block",
        sim3_rig_to_object_init=Sim3.identity(),
        sim3_rig_to_object=Sim3.identity(),
        cameras=cams,
        preset="test",
        choices={},
        timings_s={},
        losses={},
        gaussians=g,
        means_canonical=s.means,
        face_index=s.face_index,
        barycentrics=s.barycentrics,
        part_label=s.part_label,
        part_names=parts.part_names,
    )
    save_twin(twin, path, mesh_cad=parts, mesh_deformed=ball_and_block(dent_m))
    return twin


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    root = tmp_path_factory.mktemp("view") / "twin"
    return make_twin(root, dent_m=0.003)


def get(port: int, path: str, headers: dict | None = None, method: str = "GET") -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    conn.request(method, path, headers=headers or {})
    resp = conn.getresponse()
    resp.body = resp.read()
    conn.close()
    return resp


class Serving:
    def __init__(self, server: ViewServer):
        self.server = server
        self.thread = threading.Thread(target=server.serve_forever, daemon=True)

    def __enter__(self) -> ViewServer:
        self.thread.start()
        return self.server

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join()


# ------------------------------------------------------------------------------------------- the server


def test_serves_the_page_and_the_twin_files(tmp_path):
    (tmp_path / "twin.json").write_text("{}")
    with Serving(ViewServer(ViewRoots(tmp_path))) as server:
        assert server.server_address[0] == "127.0.0.1"
        page = get(server.port, "/")
        assert page.status == 200 and b"/web/view.js" in page.body
        doc = get(server.port, "/twin/twin.json")
        assert doc.status == 200 and doc.body == b"{}" and doc.getheader("Content-Type") == "application/json"
        assert get(server.port, "/web/view.js").getheader("Content-Type").startswith("text/javascript")


def test_refuses_every_path_outside_the_twin(tmp_path):
    twin, outside = tmp_path / "twin", tmp_path / "secret"
    twin.mkdir()
    outside.mkdir()
    (outside / "key.txt").write_text("secret")
    (twin / "twin.json").write_text("{}")
    (twin / "out").symlink_to(outside)
    (twin / "key.txt").symlink_to(outside / "key.txt")
    (twin / ".twin.incoming").mkdir()
    (twin / ".twin.incoming" / "twin.json").write_text("{}")
    roots = ViewRoots(twin)
    for path in (
        "/twin/../secret/key.txt",
        "/twin/%2e%2e/secret/key.txt",
        "/twin/out/key.txt",
        "/twin/key.txt",
        "/twin//etc/passwd",
        "/twin/.twin.incoming/twin.json",
        "/twin/",
        "/etc/passwd",
        "/inspection/inspection.json",
        "/web/../../calibration/guard.py",
    ):
        assert resolve_url_path(roots, path) is None, path
    with Serving(ViewServer(roots)) as server:
        for path in ("/twin/../secret/key.txt", "/twin/%2e%2e/secret/key.txt", "/twin/out/key.txt", "/twin/key.txt"):
            resp = get(server.port, path)
            assert resp.status == 404 and b"secret" not in resp.body, path
        assert get(server.port, "/twin/twin.json", method="POST").status == 501
        assert get(server.port, "/twin/twin.json", method="PUT").status == 501
        # A page elsewhere reaching 127.0.0.1 through a name of its own (DNS rebinding) is refused.
        assert get(server.port, "/twin/twin.json", headers={"Host": "attacker.example:80"}).status == 403


def test_any_other_interface_needs_the_token(tmp_path):
    (tmp_path / "twin.json").write_text("{}")
    with pytest.raises(ValueError, match="token"):
        ViewServer(ViewRoots(tmp_path), "0.0.0.0", 0, None)
    with Serving(ViewServer(ViewRoots(tmp_path), "0.0.0.0", 0, "s3cret-token")) as server:
        assert "token=s3cret-token" in server.url()
        assert get(server.port, "/twin/twin.json").status == 403
        assert get(server.port, "/twin/twin.json?token=wrong").status == 403
        ok = get(server.port, "/?token=s3cret-token")
        assert ok.status == 200
        cookie = ok.getheader("Set-Cookie").split(";")[0]
        # The page's own requests carry the cookie, not the query.
        assert get(server.port, "/twin/twin.json", headers={"Cookie": cookie}).status == 200
        assert get(server.port, "/twin/twin.json", headers={"Cookie": "cadsplat_view=wrong"}).status == 403


def test_bad_targets_exit_with_one_sentence(tmp_path, capsys):
    from deploy.cli import main

    assert main(["view", str(tmp_path)]) != 0
    assert "is not a twin" in capsys.readouterr().err
    (tmp_path / "jobs").mkdir()
    assert main(["view", "--work", str(tmp_path), "../../etc"]) != 0
    assert "outside" in capsys.readouterr().err
    assert main(["view", "--work", str(tmp_path), "cap-1"]) != 0
    assert "no finished twin" in capsys.readouterr().err


@needs_vendor
@pytest.mark.parametrize("as_job", [False, True])
def test_the_command_binds_loopback_prints_the_url_and_stops_on_sigterm(tmp_path, twin, as_job):
    if as_job:
        job = tmp_path / "work" / "jobs" / "cap-1"
        job.mkdir(parents=True)
        (job / "twin").symlink_to(twin.root, target_is_directory=True)
        args = ["view", "--work", str(tmp_path / "work"), "cap-1"]
    else:
        args = ["view", str(twin.root)]
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:") and "token" not in url, (url, proc.stderr.read() if proc.poll() is not None else "")
        port = int(url.split(":")[2].rstrip("/"))
        assert get(port, "/twin/twin.json").status == 200
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# ------------------------------------------------------------------------------------------- in the browser


@pytest.fixture(scope="module")
def chromium():
    binary = chromium_binary()
    if binary is None or not SPARK.is_file():
        pytest.skip("needs chromium and the vendored three.js and Spark (`make env`)")
    browser = Chromium(binary)
    yield browser
    browser.close()


def over_white(shot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A screenshot RGBA uint8 [H, W, 4] (straight alpha) as rgb over white [H, W, 3] in [0, 1], and its alpha [H, W]."""
    a = shot[..., 3:] / 255.0
    return shot[..., :3] / 255.0 * a + (1.0 - a), a[..., 0]


@needs_vendor
@needs_chromium
@pytest.mark.parametrize("index", [0, 5])
def test_the_page_at_a_training_camera_is_the_engine_render(twin, chromium, index):
    """Spark in Chromium draws the twin's splats.ply as the engine does: a sign, order, activation or colour-space
    slip anywhere costs more than the margin (the controls: the same splats with one convention broken)."""
    cam = twin.cameras[index].camera
    with Serving(ViewServer(ViewRoots(twin.root))) as server:
        shot, _ = chromium.screenshot(server.url(f"camera={index}"), cam.width, cam.height)
    rgb, alpha = over_white(shot)

    def engine(g: Gaussians) -> tuple[np.ndarray, np.ndarray]:
        out, a = render(g, cam.viewmat[None], cam.K[None], cam.width, cam.height)
        return out[0].numpy(), a[0].numpy()

    want, want_alpha = engine(twin.gaussians)
    obj = (want_alpha > 0.5) | (alpha > 0.5)
    assert iou(want_alpha > 0.5, alpha > 0.5) >= 0.95
    assert psnr_over(rgb, want, obj) >= 25.0
    g = twin.gaussians
    broken = {
        "SH degree 1 negated": Gaussians.from_arrays(
            g.means, g.quats, g.log_scales, g.opacity_logits, np.concatenate([g.sh[:, :1], -g.sh[:, 1:4], g.sh[:, 4:]], 1)
        ),
        "quaternions read xyzw": Gaussians.from_arrays(g.means, g.quats[:, [1, 2, 3, 0]], g.log_scales, g.opacity_logits, g.sh),
    }
    for name, wrong in broken.items():
        assert psnr_over(rgb, engine(wrong)[0], obj) < 25.0, name
    assert psnr_over(rgb, want**2.2, obj) < 25.0, "colours read as linear"


@needs_vendor
@needs_chromium
def test_the_heat_map_shows_the_inspection_colours_and_verdict(tmp_path, chromium):
    from plyfile import PlyData

    from deploy.inspection_report import inspect_twin_dir
    from reconstruction.inspect import rasterize_mesh

    # The cap pushed in is a fifth of the ball: the map's least-squares best fit takes part of it as placement, and
    # 4 mm leaves the cap out of the 1 mm tolerance by more than its uncertainty.
    twin = make_twin(tmp_path / "twin", dent_m=0.004)
    doc = inspect_twin_dir(twin.root, twin.root / "inspection", tolerance_mm=1.0, max_unseen_pct=25.0, turntable=0, renders=False)
    assert doc["verdict"]["status"] == "FAIL"
    ply = PlyData.read(str(twin.root / "inspection" / "deviation.ply"))
    v = ply["vertex"]
    vertices = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    colours = np.stack([v["red"], v["green"], v["blue"]], 1) / 255.0
    faces = np.stack(ply["face"]["vertex_indices"]).astype(np.int64)
    cam = twin.cameras[0].camera
    with Serving(ViewServer(ViewRoots(twin.root, twin.root / "inspection"))) as server:
        shot, verdict = chromium.screenshot(
            server.url("camera=0&layers=heatmap"), cam.width, cam.height, probe="document.getElementById('verdict').textContent"
        )
    assert verdict == doc["verdict"]["line"]
    _, face_id, bary = rasterize_mesh(vertices, faces, cam)
    hit = face_id >= 0
    want = np.ones((cam.height, cam.width, 3))
    want[hit] = np.einsum("pk,pkd->pd", bary[hit], colours[faces[face_id[hit]]])
    rgb, alpha = over_white(shot)
    assert iou(hit, alpha > 0.5) >= 0.95
    assert psnr_over(rgb, want, hit & (alpha > 0.5)) >= 30.0
    # The dent's colour (blue: inside the CAD by more than the tolerance) is on screen where the engine puts it.
    blue = (want[..., 2] > 0.6) & (want[..., 0] < 0.3) & hit
    assert blue.sum() > 20
    assert np.abs(rgb[blue] - want[blue]).mean() < 0.05


@needs_vendor
@needs_chromium
def test_the_spz_export_read_by_spark_is_the_engine_render(tmp_path, chromium):
    """The .spz export (Niantic's layout, +Y up) through Spark's own .spz loader, turned back into the object frame."""
    from simulation.export import export_spz, gltf_frame

    twin = make_twin(tmp_path / "twin")
    export_spz(twin.root, twin.root / "splats.spz")
    _, gltf_from_object = gltf_frame(twin)
    frame = ",".join(f"{x:.17g}" for x in np.linalg.inv(gltf_from_object).ravel())
    cam = twin.cameras[0].camera
    with Serving(ViewServer(ViewRoots(twin.root))) as server:
        shot, _ = chromium.screenshot(server.url(f"camera=0&splats=splats.spz&frame={frame}"), cam.width, cam.height)
    rgb, alpha = over_white(shot)
    want, want_alpha = (x[0].numpy() for x in render(twin.gaussians, cam.viewmat[None], cam.K[None], cam.width, cam.height))
    assert iou(want_alpha > 0.5, alpha > 0.5) >= 0.95
    assert psnr_over(rgb, want, (want_alpha > 0.5) | (alpha > 0.5)) >= 25.0


def test_the_kiosk_names_the_command_that_opens_the_last_twin():
    from deploy.kiosk import render_work
    from deploy.kiosk_state import ApplianceState, Verdict

    screen = render_work(ApplianceState(last_twin=Verdict("cap-1", "m", 0.9, 0.95, "Good", "ok", "/w/jobs/cap-1/twin/renders/cam00.png")))
    assert "view: cadsplat view /w/jobs/cap-1/twin" in screen


NODE_MODULES = Path(sys.prefix) / "node" / "node_modules"  # where `make env` installs the npm packages (.venv/node)


@needs_chromium
def test_the_khr_glb_read_by_babylon_is_the_engine_render(tmp_path, chromium):
    """The KHR_gaussian_splatting GLB export (+Y up) through Babylon.js's glTF loader, drawn from a training camera.

    Babylon composites over an opaque white page as the engine does over white. On a transparent canvas its colour
    channels are the engine's premultiplied colour, but its alpha is not: its splat material blends with
    ALPHA_COMBINE, whose alpha factors (ONE, ONE) add the splats' alphas instead of compositing them, so the
    silhouette alone is taken from there. Babylon dilates by a quarter of its kernelSize (the page sets 4 eps2d):
    its default 0.3 draws the engine's eps2d / 4 (benchmarks/results/view_browser.md)."""
    if not (NODE_MODULES / "babylonjs-loaders" / "babylonjs.loaders.min.js").is_file():
        pytest.skip(f"Babylon.js is not installed under {NODE_MODULES} (`make env`)")
    from simulation.export import export_glb, gltf_frame

    twin = make_twin(tmp_path / "twin")
    export_glb(twin.root, twin.root / "splats.glb")
    _, gltf_from_object = gltf_frame(twin)
    frame = ",".join(f"{x:.17g}" for x in gltf_from_object.ravel())
    cam = twin.cameras[0].camera
    page = Path(__file__).resolve().parents[1] / "khr_page"

    def engine(g: Gaussians, background="white") -> tuple[np.ndarray, np.ndarray]:
        kw = {} if background == "white" else {"background": None}
        out, a = render(g, cam.viewmat[None], cam.K[None], cam.width, cam.height, **kw)
        return out[0].numpy(), a[0].numpy()

    with Serving(ViewServer(ViewRoots(twin.root, web=page, vendor=NODE_MODULES))) as server:
        shots, kernels = {}, {}
        for q in ("", "&background=white", "&background=white&kernel=0.3"):
            shots[q], kernels[q] = chromium.screenshot(
                server.url(f"camera=0&frame={frame}{q}"), cam.width, cam.height, probe="window.cadsplatKernelSize"
            )
    # The page draws with 4 eps2d, the eps2d read from the GLB's extras.
    assert kernels[""] == pytest.approx(4 * twin.gaussians.eps2d)
    want, want_alpha = engine(twin.gaussians)
    alpha = shots[""][..., 3] / 255.0
    assert iou(want_alpha > 0.5, alpha > 0.5) >= 0.95
    obj = (want_alpha > 0.5) | (alpha > 0.5)
    assert psnr_over(shots["&background=white"][..., :3] / 255.0, want, obj) >= 25.0
    premultiplied, _ = engine(twin.gaussians, background=None)
    assert psnr_over(shots[""][..., :3] / 255.0 * alpha[..., None], premultiplied, obj) >= 25.0
    # Babylon's own default kernel draws the engine's splats dilated by a quarter of it, not by all of it.
    default_kernel = shots["&background=white&kernel=0.3"][..., :3] / 255.0
    quarter, _ = engine(replace(twin.gaussians, eps2d=0.3 / 4))
    assert psnr_over(default_kernel, quarter, obj) > psnr_over(default_kernel, want, obj) + 3.0
