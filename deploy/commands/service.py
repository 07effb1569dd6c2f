"""`cadsplat service run|status|retry|history`: the pipeline service over a capture store."""

from __future__ import annotations

import time
from pathlib import Path

import click


@click.group(help="The pipeline service: committed captures -> registered -> reconstructed -> exported twins.")
def service() -> None:
    pass


@service.command("run", help="Serve: pick up committed captures from STORE and turn each into a twin under WORK.")
@click.option("--store", "store", required=True, type=click.Path(path_type=Path), help="The rig's capture store.")
@click.option("--work", "work", required=True, type=click.Path(path_type=Path), help="Job store and twins.")
@click.option("--library", "library", required=True, type=click.Path(exists=True, path_type=Path), help="CAD library.")
@click.option("--preset", default="cpu", type=click.Choice(["preview", "cpu", "paper"]), show_default=True)
@click.option("--max-queue", default=8, show_default=True, help="Jobs waiting at most; more captures wait in the store.")
@click.option("--max-jobs", default=None, type=int, help="Stop after this many jobs (default: serve until SIGTERM).")
@click.option("--poll", default=2.0, show_default=True, help="Seconds between scans of the store.")
@click.option(
    "--inspect-tolerance",
    "tolerance_mm",
    default=None,
    type=click.FloatRange(min=0.0, min_open=True),
    help="Inspect every twin against its CAD at this tolerance, mm (`cadsplat inspect`); the verdict goes in the job record.",
)
@click.option(
    "--max-unseen",
    "max_unseen_pct",
    default=None,
    type=click.FloatRange(0.0, 100.0),
    help="With --inspect-tolerance: unseen surface share (%) above which the verdict is UNCERTAIN.",
)
@click.option(
    "--min-free-gb", default=0.25, show_default=True, type=click.FloatRange(0), help="Claim no job while WORK has less free disk than this."
)
@click.option(
    "--rig-config",
    default=None,
    type=click.Path(dir_okay=False, path_type=Path),
    help="The line's rig.toml: its [registration], [inspection] and [limits] apply to every capture (flags above win).",
)
def run(
    store: Path,
    work: Path,
    library: Path,
    preset: str,
    max_queue: int,
    max_jobs: int | None,
    poll: float,
    tolerance_mm: float | None,
    max_unseen_pct: float | None,
    min_free_gb: float,
    rig_config: Path | None,
) -> None:
    from deploy.service import PipelineService
    from deploy.steps import make_step_runner, pipeline_config

    def show(e) -> None:
        if e.kind == "stopped":
            click.echo(e.detail["error"])
            return
        if e.kind == "resumed":
            click.echo("RESUMED: disk space is back; serving jobs again")
            return
        detail = e.detail.get("error", "") if e.kind in ("job-failed", "job-retry") else e.detail.get("inspection", {}).get("line", "")
        click.echo(f"{e.kind:<12} job {e.job_id} {e.capture_id} {e.step} {detail}".rstrip())

    rig = None
    if rig_config is not None:
        from rig.config import load_config

        rig = load_config(rig_config)
    cfg = pipeline_config(
        library, preset, rig=rig, rig_toml=rig_config, inspection_tolerance_mm=tolerance_mm, inspection_max_unseen_pct=max_unseen_pct
    )
    svc = PipelineService(store, work, make_step_runner(cfg), max_queue=max_queue, on_event=show, min_free_bytes=int(min_free_gb * 1e9))
    requeued = sum(j.status == "queued" for j in svc.recovered)
    if requeued:
        click.echo(f"resumed: {requeued} interrupted step(s) will be redone; finished steps are kept")
    done = svc.run_forever(poll_s=poll, max_jobs=max_jobs)
    click.echo(f"stopped after {done} job(s)")


@service.command("status", help="One line per job: its status, the step it is at, and any error.")
@click.option("--work", "work", required=True, type=click.Path(exists=True, path_type=Path))
def status(work: Path) -> None:
    from deploy.jobs import JobStore

    jobs = JobStore(work / "jobs.sqlite").jobs()
    if not jobs:
        click.echo("no jobs yet")
    for j in jobs:
        verdict = j.steps["reconstruct"]["output"].get("inspection", {}).get("line", "")
        click.echo(f"{j.id:>4} {j.capture_id:<28} {j.status:<8} step {j.current_step:<11} {j.error or verdict}".rstrip())


@service.command("retry", help="Put job JOB_ID back in the queue (after fixing what made it fail).")
@click.argument("job_id", type=int)
@click.option("--work", "work", required=True, type=click.Path(exists=True, path_type=Path))
def retry(job_id: int, work: Path) -> None:
    from deploy.jobs import JobStore

    store = JobStore(work / "jobs.sqlite")
    job = store.get(job_id)
    store.retry(job_id)
    click.echo(f"job {job_id} ({job.capture_id}) queued again")


@service.command("history", help="Inspection verdicts of finished jobs, per part id (the CAD model each capture was registered to).")
@click.option("--work", "work", required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--part", "part", default=None, help="Only this part id.")
def history(work: Path, part: str | None) -> None:
    from deploy.jobs import JobStore
    from deploy.steps import inspection_history

    jobs = JobStore(work / "jobs.sqlite").jobs()
    found = inspection_history(jobs, part)
    # A failed job was never registered to a part: listed when no part is asked for, so a given-up capture is seen.
    failed = [j for j in jobs if j.status == "failed"] if part is None else []
    if not found and not failed:
        click.echo("no inspected jobs yet" + (f" of part {part}" if part else ""))
    for model_id, rows in found.items():
        counts = {s: sum(r["status"] == s for r in rows) for s in ("PASS", "FAIL", "UNCERTAIN")}
        click.echo(f"{model_id}: {len(rows)} inspected, " + ", ".join(f"{n} {s}" for s, n in counts.items()))
        for r in rows:
            when = time.strftime("%Y-%m-%d %H:%M", time.localtime(r["finished"])) if r["finished"] else ""
            click.echo(f"  {when}  {r['capture_id']:<28} {r['line']}")
    if found:
        click.echo(f"open one in the browser: cadsplat view --work {work} CAPTURE_ID")
    if failed:
        click.echo(f"no twin: {len(failed)} failed job(s) (`cadsplat service retry JOB_ID` after fixing the cause)")
        for j in failed:
            click.echo(f"  job {j.id:<4} {j.capture_id:<28} FAILED {j.error}")
