"""What the benchmark scripts share: where the repository, its results and the shared data live, the
machine reading their speed tables state (the anchor step, the CPU, the load) and the ratio of a time to
that anchor, how a results file is rewritten without losing what people wrote in it, the CAD variants of the synthetic scenes (decimated, smoothly deformed)
and the engine switches of each evaluated method."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
SHARED = Path(os.environ.get("CADSPLAT_SHARED_DATA", REPO.parent / "shared" / "data"))


def gltf_validator() -> tuple[str, Path] | None:
    """(node, the node_modules directory holding the Khronos gltf-validator) or None when either is absent.
    Looked for in CADSPLAT_GLTF_VALIDATOR, then where `make env` installs it (.venv/node), then npm's global root."""
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None:
        return None
    roots = [os.environ.get("CADSPLAT_GLTF_VALIDATOR", ""), str(REPO / ".venv" / "node")]
    if shutil.which("npm"):
        roots.append(subprocess.run(["npm", "root", "-g"], capture_output=True, text=True).stdout.strip())
    for root in filter(None, roots):
        mods = Path(root) if Path(root).name == "node_modules" else Path(root) / "node_modules"
        if (mods / "gltf-validator").is_dir():
            return node, mods
    return None


def cpu_line(cpuinfo: str | None = None) -> str:
    """'AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16': what the speed tables were measured on. The
    rasterizer's fp64 lanes (AVX2 or AVX-512) and the deformation field's bfloat16 path (AVX512-BF16, AMX) move
    the engine's timings more than the machine reference (a torch workload) shows: 607-741 against ~1000 ms there,
    26 against 57 s a rig scene, from the Intel CPU with AVX-512 and AMX to the AMD one with AVX2."""
    text = Path("/proc/cpuinfo").read_text() if cpuinfo is None else cpuinfo
    fields: dict[str, str] = {}
    for key, _, value in (line.partition(":") for line in text.splitlines() if ":" in line):
        fields.setdefault(key.strip(), value.strip())  # the first processor's
    flags = set(fields.get("flags", "").split())
    model = fields.get("model name", "unknown CPU")
    vector = "AVX-512" if "avx512f" in flags else "AVX2 (no AVX-512)" if "avx2" in flags else "no AVX2"
    bf16 = "native bfloat16" if flags & {"avx512_bf16", "amx_bf16"} else "no native bfloat16"
    return f"{model}, {os.cpu_count()} cores, {vector}, {bf16}"


def load_line() -> str:
    """'load average 3.2 on 2 cores': the 1-minute load, to read timings taken on a shared machine."""
    return f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"


@dataclass(frozen=True)
class MachineReading:
    """What a speed table's times are stated against, read together in the run that timed them: the speed anchor's
    step in ms (`reconstruction.render.anchor`), the CPU (`cpu_line`) and the load (`load_line`)."""

    anchor_ms: float
    cpu: str
    load: str

    def x_anchor(self, seconds: float) -> str:
        """`seconds` over this reading's anchor step, formatted for an `x anchor` column (see `x_anchor`)."""
        return x_anchor(seconds, self.anchor_ms)

    def header(self) -> str:
        """The sentence a table's header text carries: the anchor step, what it is, the CPU and the load."""
        return (
            f"Anchor: {self.anchor_ms:.0f} ms a step, read in this run (`reconstruction.render.anchor`: one forward+backward of "
            f"the tiled pure-PyTorch rasterizer, 20k splats at 256²); `x anchor` is a time over that step. CPU: {self.cpu}; {self.load}."
        )


def machine_reading() -> MachineReading:
    """The anchor step, CPU and load now. The load is read first: the anchor's child process then loads the cores itself."""
    from reconstruction.render.anchor import anchor_ms

    load = load_line()
    return MachineReading(anchor_ms(), cpu_line(), load)


def x_anchor(seconds: float | None, anchor_ms: float | None) -> str:
    """'270x', '3.4x', '0.52x', '0.052x': a time over the anchor step (ms) read in the same run; '-' where either is unknown
    (a cached run from before the anchor was recorded)."""
    if seconds is None or anchor_ms is None or not math.isfinite(seconds) or not anchor_ms > 0:
        return "-"
    ratio = 1000.0 * seconds / anchor_ms
    if ratio >= 100:
        return f"{ratio:.0f}x"
    return f"{ratio:.1f}x" if ratio >= 1 else f"{ratio:.2f}x" if ratio >= 0.1 else f"{ratio:.2g}x"


def median_x_anchor(runs: list[tuple[float, float | None]]) -> str:
    """The median over runs of each run's time (s) over the anchor step (ms) read beside it, as `x_anchor` writes it;
    runs without an anchor reading (cached from before one was recorded) are left out, '-' when none has one."""
    ratios = sorted(seconds / anchor for seconds, anchor in runs if anchor and math.isfinite(seconds))
    if not ratios:
        return "-"
    mid = len(ratios) // 2
    return x_anchor(ratios[mid] if len(ratios) % 2 else (ratios[mid - 1] + ratios[mid]) / 2, 1.0)


def write_results(path: Path, generated: str) -> str:
    """Writes `generated` to the results file at `path`, then every `## ` section already there whose heading `generated`
    does not write itself: a run replaces its own tables and keeps the readings people added below them (once, however
    often it runs). Returns the text written."""
    kept: list[str] = []
    if path.exists():
        own = {line for line in generated.splitlines() if line.startswith("## ")}
        keep = False
        for line in path.read_text().splitlines(keepends=True):
            if line.startswith("## "):
                keep = line.rstrip("\n") not in own
            if keep:
                kept.append(line)
    text = generated.rstrip("\n") + "\n\n" + "".join(kept) if kept else generated
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


def symmetric_surface_distance(
    a_v: np.ndarray, a_f: np.ndarray, b_v: np.ndarray, b_f: np.ndarray, n: int, seed: int = 0
) -> tuple[float, float]:
    """Mean and p95 of closest-point distances (pooled over both directions) from `n` area-uniform samples
    of each mesh (vertices [V, 3], faces [F, 3]) to the other mesh's surface, exact point-to-triangle.
    Against the other mesh's samples instead, two samplings of one surface would already lie 0.3-0.5 % of
    the diameter apart at 20k samples (rig scenes' clamp and cube), a floor under every figure."""
    from reconstruction.inspect import surface_distance
    from reconstruction.splats import sample_surface

    rng = np.random.default_rng(seed)
    pa, _, _ = sample_surface(a_v, a_f, n, rng)
    pb, _, _ = sample_surface(b_v, b_f, n, rng)
    d = np.concatenate([surface_distance(pa, b_v, b_f), surface_distance(pb, a_v, a_f)])
    return float(d.mean()), float(np.percentile(d, 95))


def decimate(mesh: trimesh.Trimesh, keep: float) -> trimesh.Trimesh:
    """`mesh` simplified to the fraction `keep` of its faces."""
    import fast_simplification

    v, f = fast_simplification.simplify(mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32), target_reduction=1.0 - keep)
    return trimesh.Trimesh(v.astype(np.float64), f, process=False)


def deform(mesh: trimesh.Trimesh, amplitude: float, seed: int) -> trimesh.Trimesh:
    """Smooth deformation: a sum of low-frequency sinusoids, `amplitude` x the model radius at most."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices
    c = v.mean(0)
    r = float(np.linalg.norm(v - c, axis=1).max())
    out = v.copy()
    for _ in range(3):
        k = rng.normal(size=3) / r * 1.5
        a = rng.normal(size=3)
        out += amplitude * r / 3 * np.outer(np.sin((v - c) @ k + rng.uniform(0, 2 * np.pi)), a / np.linalg.norm(a))
    return trimesh.Trimesh(out, mesh.faces, process=False)


def engine_kwargs(method: str, preset: str, cuda: bool) -> dict:
    """`pipeline.reconstruct_capture` keyword arguments for a method (full | an ablation of `presets.ABLATIONS` |
    sphere-init): ablations and the sphere init are engine switches; the `paper` preset runs its
    iterations / 30 on a CPU."""
    from reconstruction.presets import ABLATIONS, PAPER

    kw: dict = {}
    if method == "sphere-init":
        kw["init"] = "sphere"
    elif method in ABLATIONS:
        kw["ablations"] = [method]
    elif method != "full":
        raise ValueError(f"unknown method {method!r}")
    if preset == "paper" and not cuda:
        kw["overrides"] = {
            "iters_pose": PAPER.iters_pose // 30,
            "iters_deform": PAPER.iters_deform // 30,
            "iters_photo": PAPER.iters_photo // 30,
            "dropout_anneal": PAPER.dropout_anneal // 30,
        }
    return kw
