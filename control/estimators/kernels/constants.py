"""The kernels' constants, which the Python estimators share (numpy and numba both free of them)."""
ETA_BLEND_SIGMA = 1.0          # the free-eta estimate is blended in over this many more sigma of evidence
ETA_PRIOR_LIMIT = 4.0          # an eta ratio further than this many prior sigmas from 1 is a model failure
K_MIN = 0.2                    # floor of the eta ratio k when dividing by it (its prior is 1 +- 25 % at most)
GATE_HPH_RATIO = 0.1           # NIS gating starts once H P H^T is this small against R
