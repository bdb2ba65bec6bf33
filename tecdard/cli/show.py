"""What the command line prints for people: task results, `status` and the progress line, in mm and
degrees (`--json` prints the daemon's own SI messages instead)."""
from __future__ import annotations

import math

M_TO_MM = 1e3
THREAD_ROWS = 12               # `status` shows the busiest threads only
# result fields in metres, by name, and how each is labelled
LENGTHS_M = {"radius": "lever arm", "lever_arm": "lever arm", "travel": "travel", "distance": "distance"}


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def mm(v) -> str:
    """A position or a one-sigma (m) as "[x, y, z] mm"; "-" for anything that is not numbers."""
    if isinstance(v, (list, tuple)) and v and all(_finite(x) for x in v):
        return "[" + ", ".join(f"{x * M_TO_MM:.1f}" for x in v) + "] mm"
    if _finite(v):
        return f"{v * M_TO_MM:.1f} mm"
    return "-"


def _axis(v) -> str:
    if isinstance(v, (list, tuple)) and len(v) == 3 and all(_finite(x) for x in v):
        return "[" + ", ".join(f"{x:.3f}" for x in v) + "]"
    return "-"


def _rows(rows: list[tuple[str, str]]) -> list[str]:
    width = max((len(k) for k, _ in rows), default=0)
    return [f"  {k:<{width}}  {v}" for k, v in rows]


def result_lines(verb: str, result: dict) -> list[str]:
    """A task's `task_done` result as a short table: positions in mm, angles in degrees."""
    rows: list[tuple[str, str]] = []
    contact = result.get("hinge") if isinstance(result.get("hinge"), dict) else result
    if "p" in contact:
        name = "hinge" if "hinge" in result else "TCP" if verb == "home" else "contact"
        rows.append((name, mm(contact.get("p"))))
        if "std" in contact:
            rows.append(("one-sigma", mm(contact.get("std"))
                         + ("  (along the axis it is unobservable)" if contact.get("axis") else "")))
        if contact.get("axis") is not None:
            rows.append(("axis", _axis(contact.get("axis"))))
    if _finite(result.get("angle_deg")):
        rows.append(("angle", f"{result['angle_deg']:.1f} deg"))
    for key, label in LENGTHS_M.items():
        if _finite(result.get(key)):
            rows.append((label, mm(result[key])))
    if _finite(result.get("turns")):
        rows.append(("turns", f"{result['turns']:.2f}"))
    if isinstance(result.get("strategy"), str):
        rows.append(("strategy", result["strategy"]))
    summary = result.get("summary")
    if isinstance(summary, dict):
        for key in ("points", "valid", "passes"):
            if isinstance(summary.get(key), int):
                rows.append((f"{key} points" if key == "valid" else key, str(summary[key])))
        if isinstance(summary.get("invalid"), dict) and summary["invalid"]:
            rows.append(("invalid", ", ".join(f"{k} {v}" for k, v in summary["invalid"].items())))
    if isinstance(result.get("path"), str):
        rows.append(("files", result["path"]))
    if isinstance(result.get("q"), list) and all(_finite(x) for x in result["q"]):
        rows.append(("joints", "[" + ", ".join(f"{math.degrees(x):.1f}" for x in result["q"]) + "] deg"))
    return [f"{verb} done"] + _rows(rows)


def gripper_text(g: dict) -> str:
    """A gripper's state in words: what it holds, its opening (mm) and its force (N, and where that came from)."""
    held = {True: "holding", False: "holding nothing", None: "cannot say what it holds"}.get(g.get("grasped"),
                                                                                              "cannot say")
    parts = [f"{g.get('kind', '?')}: {held}"]
    if _finite(g.get("width_m")):
        parts.append(f"opening {g['width_m'] * M_TO_MM:.1f} mm")
    if _finite(g.get("force_n")):
        parts.append(f"force {g['force_n']:.0f} N ({g.get('force_source', '?')})")
    if g.get("fault"):
        parts.append(f"fault: {g['fault']}")
    return ", ".join(parts)


def status_lines(state: dict) -> list[str]:
    """`status` as a short table."""
    rows = [("mode", str(state.get("mode", "-")))]
    task = state.get("task")
    rows.append(("task", "-" if not task else
                 f"{task.get('id')} ({task.get('phase')}, {100 * float(task.get('progress') or 0):.0f} %)"))
    faults = state.get("faults") or []
    rows.append(("faults", "none" if not faults else "; ".join(f"{f.get('code')}: {f.get('message')}"
                                                                for f in faults if isinstance(f, dict))))
    tcp = state.get("tcp") or {}
    rows.append(("TCP", mm(tcp.get("p"))))
    v = tcp.get("v")
    if isinstance(v, list) and all(_finite(x) for x in v):
        rows.append(("TCP speed", f"{math.hypot(*v) * M_TO_MM:.1f} mm/s"))
    contact = state.get("contact")
    if isinstance(contact, dict):
        rows.append(("contact", f"{mm(contact.get('p'))} +- {mm(contact.get('std'))}"
                     + (f", turned {contact['angle_deg']:.1f} deg" if _finite(contact.get("angle_deg")) else "")))
    else:
        rows.append(("contact", "none"))
    imu = state.get("imu")
    if isinstance(imu, dict):
        rate = imu.get("rate_hz")
        rows.append(("IMU", (f"{rate:.0f} samples/s" if _finite(rate) else "no rate yet")
                     + (f", {imu['part']}" if isinstance(imu.get("part"), str) else "")))
    if isinstance(state.get("gripper"), dict):
        rows.append(("gripper", gripper_text(state["gripper"])))
    ctl = state.get("control") or {}
    if ctl:
        late = ctl.get("late_ms_p99")
        rows.append(("control", f"{ctl.get('ticks', '-')} ticks, {ctl.get('overruns', '-')} overruns"
                     + (f", lateness p99 {late:.2f} ms" if _finite(late) else "")))
    threads = state.get("threads")
    per_thread: list[tuple[str, str]] = []
    if isinstance(threads, dict) and threads:
        rows.append(("threads", "CPU of one core, last 5 s; the longest wait to run once due"))
        for name, row in list(threads.items())[:THREAD_ROWS]:
            if isinstance(row, dict) and _finite(row.get("cpu_pct")):
                wake = row.get("wake_ms_max")
                per_thread.append((str(name), f"{row['cpu_pct']:.1f} %" + (f", waited up to {wake:.2f} ms"
                                                                            if _finite(wake) else "")))
    # the threads' names are a table of their own under their row: a long one (imu-acquisition)
    # does not widen the state's
    return _rows(rows) + ["  " + line for line in _rows(per_thread)]


def progress_text(state: dict | None, start_p: list | None) -> str | None:
    """The progress line: bar, percent, phase, the object's angle and the TCP's travel (mm)."""
    task = (state or {}).get("task")
    if not task:
        return None
    try:
        frac = max(0.0, min(1.0, float(task.get("progress", 0.0))))
    except (TypeError, ValueError):
        frac = 0.0
    width = 30
    filled = int(round(frac * width))
    text = f"[{'#' * filled}{'.' * (width - filled)}] {frac * 100:5.1f}% {task.get('phase', '')}"
    contact = state.get("contact")
    if isinstance(contact, dict) and _finite(contact.get("angle_deg")):
        text += f"  turned {contact['angle_deg']:.1f} deg"
    p = (state.get("tcp") or {}).get("p")
    if start_p is not None and isinstance(p, list) and len(p) == 3 and all(_finite(x) for x in p):
        text += f"  moved {math.dist(p, start_p) * M_TO_MM:.1f} mm"
    return text
