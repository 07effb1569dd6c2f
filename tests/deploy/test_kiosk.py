"""The operator screen, headless (Textual's pilot), against the simulated appliance."""

import asyncio
import time

import pytest

from deploy.kiosk import Kiosk, render_alarms, render_calibration
from deploy.kiosk_state import ApplianceState, CameraStatus, drift_alarm, grade_twin


def test_thirteen_cameras_fit_an_80x24_screen():
    cams = tuple(CameraStatus(f"cam{i:02d}", True, "RECALIBRATE" if i == 3 else "OK", 0.4 if i == 3 else 0.01) for i in range(13))
    text = render_calibration(ApplianceState(cameras=cams))
    assert len(text.splitlines()) == 1 + 7
    assert max(len(line) for line in text.splitlines()) <= 42


def test_alarm_and_grade_words():
    alarm = drift_alarm(CameraStatus("cam03", True, "WARN", 0.4))
    assert alarm.text == "Camera cam03 moved 0.4° — run calibration check."
    assert "not answering" in drift_alarm(CameraStatus("cam01", False)).text
    assert drift_alarm(CameraStatus("cam01", True, "OK", 0.01)) is None
    assert grade_twin(0.93, 0.95)[0] == "Good" and grade_twin(0.5, 0.95)[0] == "Poor"


async def wait_for(app: Kiosk, pilot, predicate, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        await pilot.pause(0.5)
        text = app.screen_text()
        if predicate(text):
            return text
    raise AssertionError("screen never showed what was expected:\n" + app.screen_text())


@pytest.mark.slow
def test_simulated_appliance_end_to_end_on_screen(tmp_path):
    from deploy.appliance import Appliance

    backend = Appliance.simulated(tmp_path / "appliance", views=6, preset="preview", interval_s=3600)
    app = Kiosk(backend)

    async def drive() -> tuple[str, str]:
        async with app.run_test(size=(80, 24)) as pilot:
            await pilot.press("t")  # one part, taken by the software trigger
            verdict = await wait_for(app, pilot, lambda t: "LAST TWIN 000000" in t, 600)
            backend.knock("cam02", 1.5)
            await pilot.press("t")
            alarm = await wait_for(app, pilot, lambda t: "Camera cam02 moved" in t, 300)
            await pilot.press("a")
            await pilot.pause(0.5)
            acked = app.screen_text()
            await pilot.press("q")
            return verdict, alarm + "\n---\n" + acked

    try:
        verdict, alarm = asyncio.run(drive())
    finally:
        backend.close()
    print(verdict, alarm, sep="\n=====\n")
    assert "captures 1" in verdict and "model medium_clamp_cad" in verdict
    assert any(g in verdict for g in ("GOOD", "USABLE", "POOR")) and "fit IoU" in verdict
    assert "Camera cam02 moved 1.5° — stop the line and run a calibration" in alarm
    assert alarm.split("---")[1].count("ALARM (") == 0


def test_disk_full_is_a_state_on_screen_and_in_the_rig_log(capsys):
    from deploy.commands.rig import _report
    from deploy.kiosk import render_rig
    from rig.acquisition import Outcome
    from rig.triggers import TriggerEvent

    text = render_rig(ApplianceState(watching=True, disk_full="STOPPED: disk full: 0.00 GB free"))
    assert text.splitlines()[0] == "RIG STOPPED: disk full"
    ev = lambda seq: TriggerEvent(seq, "can", 0)  # noqa: E731
    why = "STOPPED: disk full: no room to reserve 0.1 MB for the next capture; captures resume when space is freed"
    for out in (
        Outcome("refused", ev(7), reason=why, state_change="stopped"),
        Outcome("refused", ev(8), reason=why),
        Outcome("refused", ev(9), reason=why),
        Outcome("committed", ev(10), "000004-x", state_change="resumed"),
    ):
        _report(out)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3 and lines[0].startswith("STOPPED: disk full") and "trigger 7 and those after it" in lines[0]
    assert lines[1] == "RESUMED: disk space is back; capturing again" and lines[2].startswith("committed 000004-x")


def test_the_kiosk_imports_what_a_read_only_store_left_in_the_spill(tmp_path):
    from deploy.appliance import Appliance
    from tests.rig.test_store import _spilled

    work = tmp_path / "appliance"
    _, _, ids = _spilled(work, 1)
    backend = Appliance.simulated(work, views=4, size=(96, 72), preset="preview", interval_s=3600)
    try:
        assert ids[0] in backend.store.capture_ids()
        assert backend.state().message.startswith("imported 1 capture(s)")
    finally:
        backend.close()


def test_the_kiosk_shows_a_job_given_up_after_killing_the_service(tmp_path):
    """Issue 58 (8): a job whose step killed the appliance three times is given up, and the operator sees why."""
    from deploy.appliance import Appliance
    from deploy.service import PipelineService

    work = tmp_path / "appliance"
    for _ in range(3):  # three lives of the appliance's service, each ended by the same job's register step
        jobs = PipelineService(work / "store", work / "work", lambda *_: {}).jobs
        jobs.add("000000-poison", work / "store" / "captures" / "000000-poison")
        job = jobs.claim_next()
        jobs.start_step(job.id, "register")
        jobs.close()
    backend = Appliance.simulated(work, views=4, size=(96, 72), preset="preview", interval_s=3600)
    try:
        text = render_alarms(backend.state())
    finally:
        backend.close()
    assert "Capture 000000-poison failed (register: the service died during register (attempt 3 of 3); given up)" in text, text
