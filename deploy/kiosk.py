"""The operator screen: a full-screen terminal UI (Textual) for people who are not engineers.

Works over SSH, fits 80x24, and reads without colour (NO_COLOR, or `--no-color`): every state is
also spelled out in words. Keys: w start/stop watching, t take a capture now, r re-run the last
failed job, a acknowledge the alarm, b take empty-rig frames (rig empty), q quit.
"""

from __future__ import annotations

from pathlib import PurePath

from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Footer, Static

from deploy.kiosk_state import ApplianceBackend, ApplianceState


def _bar(fraction: float, width: int = 20) -> str:
    n = int(round(max(0.0, min(1.0, fraction)) * width))
    return "[" + "#" * n + "." * (width - n) + "]"


def render_rig(s: ApplianceState) -> str:
    online = sum(c.online for c in s.cameras)
    state = "STOPPED: disk full" if s.disk_full else "WATCHING" if s.watching else "STOPPED"
    return (
        f"RIG {state}\n"
        f"trigger: {s.trigger_source}\n"
        f"cameras online {online}/{len(s.cameras)}\n"
        f"last trigger: {s.last_trigger}\n"
        f"captures {s.captures}  quarantined {s.quarantined}\n"
        f"disk free {s.disk_free_gb:.1f} GB"
    )


def render_calibration(s: ApplianceState) -> str:
    """One camera a line for small rigs; two a line (states abbreviated) so 13 cameras fit 80x24."""
    two_columns = len(s.cameras) > 6
    cells = []
    for c in s.cameras:
        state = c.calibration if c.online else "OFFLINE"
        drift = f"{c.drift_deg:.1f}°" if c.drift_deg is not None else ""
        cells.append(f"{c.name[:5]:<5} {state[:5]:<5} {drift:>5}" if two_columns else f"{c.name[:8]:<8} {state:<11} {drift:>6}")
    step = 2 if two_columns else 1
    rows = ["  ".join(cells[i : i + step]) for i in range(0, len(cells), step)]
    return "\n".join(["CALIBRATION"] + rows)


def render_work(s: ApplianceState) -> str:
    lines = [f"QUEUE {len(s.queue)} waiting" + (": " + ", ".join(s.queue[:3]) if s.queue else "")]
    if s.progress:
        p = s.progress
        eta = f"ETA {p.eta_s:.0f}s" if p.eta_s is not None else ""
        lines.append(f"NOW  {p.capture_id}  {p.stage}")
        lines.append(f"     {_bar(p.fraction)} {p.fraction * 100:3.0f}% {eta}")
    else:
        lines.append("NOW  idle")
    t = s.last_twin
    if t:
        lines.append(f"LAST TWIN {t.capture_id}: {t.grade.upper()}  model {t.model_id}")
        lines.append(f"     registration {t.registration_score:.2f}  fit IoU {t.fit_iou:.2f}")
        lines.append(f"     {t.advice}")
        if t.inspection:
            lines.append(f"     PART {t.inspection}")
        if t.preview_path:
            # The preview is TWIN/renders/<view>.png: the operator gets the twin, in the browser, rather than one picture of it.
            lines.append(f"     view: cadsplat view {PurePath(t.preview_path).parents[1]}")
    else:
        lines.append("LAST TWIN none yet")
    return "\n".join(lines)


def render_alarms(s: ApplianceState) -> str:
    active = [a for a in s.alarms if not a.acknowledged]
    if not active:
        return "ALARMS none" + (f"   {s.message}" if s.message else "")
    return "\n".join([f"ALARM ({len(active)}): {active[0].text}"] + [f"  also: {a.text}" for a in active[1:2]])


class Kiosk(App):
    CSS = """
    Screen { layout: vertical; }
    #top { height: auto; }
    .panel { border: ascii; padding: 0 1; height: auto; }
    #rig { width: 34; }
    #calibration { width: 1fr; }
    """
    BINDINGS = [
        Binding("w", "watch", "Start/stop"),
        Binding("t", "trigger", "Capture now"),
        Binding("r", "rerun", "Re-run"),
        Binding("a", "ack", "Acknowledge"),
        Binding("b", "background", "Empty-rig frames"),
        Binding("q", "quit", "Quit"),
    ]

    def __init__(self, backend: ApplianceBackend, *, refresh_s: float = 0.25) -> None:
        super().__init__()
        self.backend = backend
        self.refresh_s = refresh_s
        self.title = "cadsplat"

    def compose(self) -> ComposeResult:
        with Vertical():
            with Horizontal(id="top"):
                yield Static(id="rig", classes="panel")
                yield Static(id="calibration", classes="panel")
            yield Static(id="work", classes="panel")
            yield Static(id="alarms", classes="panel")
        yield Footer()

    def on_mount(self) -> None:
        self.refresh_state()
        self.set_interval(self.refresh_s, self.refresh_state)

    def refresh_state(self) -> None:
        s = self.backend.state()
        self.query_one("#rig", Static).update(Text(render_rig(s)))
        self.query_one("#calibration", Static).update(Text(render_calibration(s)))
        self.query_one("#work", Static).update(Text(render_work(s)))
        self.query_one("#alarms", Static).update(Text(render_alarms(s)))

    def screen_text(self) -> str:
        """Everything on screen as plain text (tests and text screenshots)."""
        s = self.backend.state()
        return "\n".join([render_rig(s), render_calibration(s), render_work(s), render_alarms(s)])

    def action_watch(self) -> None:
        self.backend.toggle_watch()
        self.refresh_state()

    def action_trigger(self) -> None:
        self.backend.trigger()
        self.refresh_state()

    def action_rerun(self) -> None:
        self.backend.rerun()
        self.refresh_state()

    def action_background(self) -> None:
        self.backend.take_background()
        self.refresh_state()

    def action_ack(self) -> None:
        self.backend.acknowledge()
        self.refresh_state()

    async def action_quit(self) -> None:
        # The backend belongs to whoever started the kiosk; it closes it after the screen is gone.
        self.exit()
