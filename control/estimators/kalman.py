"""The Kalman filters: `ekf` (ours) and `paper-ekf` (the paper's, as published)."""
from control.ekf import ContactKF, PaperEKF
from control.estimators import EstimatorSpec

ESTIMATORS = (
    EstimatorSpec("ekf", "our filter on the differential constraint (eta as a state, positions as evidence)",
                  lambda params, plane: ContactKF(params.ekf, plane)),
    EstimatorSpec("paper-ekf", "the paper's EKF as published", lambda params, plane: PaperEKF(params.paper_ekf, plane)),
)
