"""DSC-like classifier data shared by the SVM and initiation tests."""
import numpy as np


def dsc_like(seed, n_traj, n_neg, radius=4.0, neg_lo=2.5, neg_hi=8.0):
    """Random-walk trajectories of 51 points drifting to the origin + failed start states."""
    rng = np.random.default_rng(seed)
    trajs = []
    for _ in range(n_traj):
        r, th = radius * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        x = r * np.array([np.cos(th), np.sin(th)])
        pts = [x.copy()]
        for _ in range(50):
            x = x - 0.08 * x / max(np.linalg.norm(x), 1e-6) + rng.normal(0, 0.06, 2)
            pts.append(x.copy())
        trajs.append(np.stack(pts))
    pos = np.concatenate(trajs).astype(np.float32) if trajs else np.zeros((0, 2), np.float32)
    r, th = rng.uniform(neg_lo, neg_hi, n_neg), rng.uniform(0, 2 * np.pi, n_neg)
    neg = np.stack([r * np.cos(th), r * np.sin(th)], -1).astype(np.float32)
    return pos, neg
