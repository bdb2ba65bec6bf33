"""`make bench`: the README's picture, docs/img/rotate.png, from one `rotate --angle-deg 30` of the whole
daemon on the simulated paper cutter, recorded as the daemon records it.

Left: the plane of rotation (world x-z, mm): the TCP's path, the true hinge and the live estimate of it
as it came, coloured by the time since the contact onset. Right: the estimate's distance from the true
hinge axis (mm, log scale) against that time, with its one-sigma in the plane of rotation.
"""
from __future__ import annotations

import pathlib
import sys
import tempfile

import numpy as np
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tecdard.api.client import Client  # noqa: E402
from tecdard.config import dump_yaml  # noqa: E402
from tecdard.recording.format import load_recording  # noqa: E402
from tecdard.recording.live import load_live  # noqa: E402
from tecdard.tools.demo import free_port, start_daemon, stop_daemon  # noqa: E402

OUT = ROOT / "docs" / "img" / "rotate.png"
ANGLE_DEG = 30.0


def record_rotate(tmp: pathlib.Path) -> tuple[pathlib.Path, dict]:
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg["zenoh"]["listen"] = [endpoint]
    cfg["record"].update(enabled=True, dir=str(tmp / "rec"))
    cfg.setdefault("map", {})["output_dir"] = str(tmp / "maps")
    path = tmp / "sim.yaml"
    path.write_text(dump_yaml(cfg))
    proc = start_daemon(str(path), endpoint)
    try:
        with Client(endpoint, robot=cfg["robot"]["name"]) as cli:
            cli.wait_alive(120, running=lambda: proc.poll() is None)
            reply = cli.command("rotate", {"angle_deg": ANGLE_DEG})
            ev = cli.wait_event(("task_done", "task_failed"), reply["task"], 120)
            if ev["kind"] != "task_done":
                raise SystemExit(f"figure: the rotate failed: {ev.get('error')}")
    finally:
        stop_daemon(proc)
    (rec_path,) = sorted((tmp / "rec").glob("*rotate*.npz"))
    return rec_path, cfg["sim"]["hinge"]


def draw(rec_path: pathlib.Path, hinge: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rec = load_recording(rec_path)
    live = load_live(rec_path, rec)
    est = live.est                                  # (k, 7): t, p, std
    onset_t = next(e["t"] for e in live.events if e.get("kind") == "contact_onset")
    p_true = np.asarray(hinge["point"], float)
    axis = np.asarray(hinge["axis"], float) / np.linalg.norm(hinge["axis"])
    after = est[:, 0] >= onset_t
    t_ms = (est[after, 0] - onset_t) * 1e3
    p = est[after, 1:4]
    d = p - p_true
    err_mm = np.linalg.norm(d - np.outer(d @ axis, axis), axis=1) * 1e3
    std_plane = np.linalg.norm(est[after, 4:7] * (1 - np.abs(axis)), axis=1) * 1e3
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4.2), constrained_layout=True)
    tcp = rec.tcp_pos * 1e3
    ax0.plot(tcp[:, 0], tcp[:, 2], color="0.3", lw=1.5, label="TCP path")
    from matplotlib.colors import LogNorm
    t_pos = np.maximum(t_ms, 1.0)
    sc = ax0.scatter(p[:, 0] * 1e3, p[:, 2] * 1e3, c=t_pos, cmap="viridis", norm=LogNorm(1.0, t_pos.max()), s=8,
                     label="hinge estimate (live)")
    ax0.plot(*(p_true[[0, 2]] * 1e3), marker="+", color="r", ms=14, mew=2, ls="none", label="true hinge")
    ax0.set_xlabel("world x, mm")
    ax0.set_ylabel("world z, mm")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.legend(loc="lower left", fontsize=8)
    ax0.set_title(f"rotate {ANGLE_DEG:g} deg about an unknown hinge (plane of rotation)", fontsize=9)
    cb = fig.colorbar(sc, ax=ax0, shrink=0.8)
    cb.set_label("time since the contact onset, ms")
    ax1.loglog(t_pos, np.maximum(err_mm, 1e-2), label="distance from the true hinge axis")
    ax1.loglog(t_pos, np.maximum(std_plane, 1e-2), ls="--", label="one-sigma in the plane of rotation")
    ax1.set_xlabel("time since the contact onset, ms")
    ax1.set_ylabel("mm")
    ax1.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=8)
    ax1.set_title(f"the estimate: {err_mm[-1]:.1f} mm off at the end", fontsize=9)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT, dpi=100)
    plt.close(fig)
    print(f"{OUT}: {len(p)} estimates; final error {err_mm[-1]:.2f} mm")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        rec_path, hinge = record_rotate(pathlib.Path(tmp))
        draw(rec_path, hinge)


if __name__ == "__main__":
    main()
