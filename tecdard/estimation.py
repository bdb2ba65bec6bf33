"""Builds the contact pipeline from the `estimator` config section (daemon and `tecdard localize` alike)."""
from __future__ import annotations

import numpy as np

from tecdard.control.baselines import BaselineParams
from tecdard.control.conditioning import GyroConditioner
from tecdard.control.ekf import ContactKfParams, PaperEkfParams
from tecdard.control.onset import OnsetDetector
from tecdard.control import estimators
from tecdard.control.pipeline import FINGERTIP_LAG_S, ContactPipeline, PipelineParams
from tecdard.config import ConfigError
from tecdard.safejson import finite, is_number, show

MAX_ETA = 100.0              # eta is 1-3 for real fingertips (the paper's 2.0 at 30 N)
MAX_GRIP_FORCE_N = 1000.0


def _eta_table(section) -> list[tuple[float, float]]:
    raw = section._raw("eta_table", [[30.0, 2.0]])
    name = f"{section.path}.eta_table"
    if not isinstance(raw, list) or not raw or len(raw) > 100:
        raise ConfigError(f"{name}: expected a list of up to 100 [grip_force_N, eta] pairs")
    out = []
    for row in raw:
        if not isinstance(row, list) or len(row) != 2 or not all(is_number(x) for x in row):
            raise ConfigError(f"{name}: expected [grip_force_N, eta] pairs, got {show(row)}")
        force, eta = finite(row[0]), finite(row[1])
        if force is None or eta is None:
            raise ConfigError(f"{name}: {show(row)} is not finite")
        if not (0.0 < eta <= MAX_ETA and 0.0 <= force <= MAX_GRIP_FORCE_N):
            raise ConfigError(f"{name}: eta must be in (0, {MAX_ETA:g}] and the force in [0, {MAX_GRIP_FORCE_N:g}] N, "
                              f"got {show(row)}")
        out.append((force, eta))
    if len({f for f, _ in out}) != len(out):
        raise ConfigError(f"{name}: a grip force appears twice")
    return out


def build_pipeline(section, R_tcp_imu: np.ndarray, odr_hz: float = 6667.0, method: str | None = None,
                   plane_normal=None) -> ContactPipeline:
    """Every option of `estimator` is read here; `method`/`plane_normal` override the config's."""
    cfg_method = section.getstr("method", "ekf", choices=estimators.names())
    cfg_plane = section.getvec3("plane_normal", None, unit=True) if section.has("plane_normal") else None
    conditioner = GyroConditioner(
        R_tcp_imu,
        eta=2.0,
        bias_tau_s=section.getfloat("bias_tau_s", 0.5, above=0.0),
        lpf_window=section.getint("gyro_lpf_window", 33, minval=1, maxval=2000),
    )
    params = PipelineParams(
        method=method or cfg_method,
        plane_normal=np.array(plane_normal if plane_normal is not None else cfg_plane)
        if (plane_normal is not None or cfg_plane is not None) else None,
        output_period_s=section.getfloat("output_period_s", 0.005, above=0.0, maxval=1.0),
        eta_table=_eta_table(section),
        grip_force_n=section.getfloat("grip_force_n", 30.0, minval=0.0, maxval=MAX_GRIP_FORCE_N),
        eta_rel_std_per_n=section.getfloat("eta_rel_std_per_n", 0.02, minval=0.0, maxval=1.0),
        arc_radial_sigma=section.getfloat("arc_radial_sigma", 0.005, minval=0.0, maxval=1.0),
        fingertip_lag_s=section.getfloat("fingertip_lag_s", FINGERTIP_LAG_S, minval=0.0, maxval=0.05),
        ekf=ContactKfParams.from_config(section.section("ekf")),
        paper_ekf=PaperEkfParams.from_config(section.section("paper_ekf")),
    )
    base = section.section("baseline")
    params.baseline = BaselineParams(window_s=base.getfloat("window_s", 0.03, above=0.0),
                                     gd_iterations=base.getint("gd_iterations", 10, minval=1, maxval=1000))
    detector = OnsetDetector.from_config(section.section("onset"), odr_hz)
    return ContactPipeline(detector, conditioner, params)
