"""The Kalman filters: `ekf` (ours) and `paper-ekf` (the paper's, as published)."""
from tecdard.control.ekf import ContactKF, PaperEKF
from tecdard.control.estimators import EstimatorSpec
from tecdard.control.reference import ReferenceKF

ESTIMATORS = (
    EstimatorSpec("ekf", "our filter on the differential constraint (eta as a state, positions as evidence)",
                  lambda params, plane: ContactKF(params.ekf, plane)),
    EstimatorSpec("ekf-reference", "`ekf` in numpy, block by block: the readable model the compiled run is tested against",
                  lambda params, plane: ReferenceKF(params.ekf, plane)),
    EstimatorSpec("paper-ekf", "the paper's EKF as published", lambda params, plane: PaperEKF(params.paper_ekf, plane)),
)
