"""The fit's linear algebra against brute force: parameters shared by the detectors."""

from __future__ import annotations

import numpy as np

from hwp_tes_systematics.diagnose.linalg import share_across_detectors


def test_shared_parameters_match_the_joint_least_squares():
    """Two detectors, each y_k = X_k a_k + noise, with a_k[S] = s_k r imposed: the
    per-detector solutions corrected by :func:`share_across_detectors` equal the joint
    least squares of the stacked system, and the chi^2 it reports is the rise of the
    joint chi^2 over the separate fits."""
    rng = np.random.default_rng(5)
    n, p, positions = 200, 4, np.array([1, 3])
    scales = np.array([[0.9, 0.9], [1.3, 1.3]])
    designs = [rng.normal(size=(n, p)) for _ in range(2)]
    r_true = np.array([0.7, -0.2])
    data = []
    for k, x in enumerate(designs):
        a = rng.normal(size=p)
        a[positions] = scales[k] * r_true + rng.normal(0, 0.05, 2)  # nearly shared
        data.append(x @ a + rng.normal(size=n))
    values = [np.linalg.lstsq(x, y, rcond=None)[0] for x, y in zip(designs, data, strict=True)]
    covariances = [np.linalg.inv(x.T @ x) for x in designs]
    separate = sum(
        float(np.sum((y - x @ a) ** 2)) for x, y, a in zip(designs, data, values, strict=True)
    )

    shared, _, r, cov_r, cost = share_across_detectors(values, covariances, positions, scales)

    # joint: unknowns (a_0 free, a_1 free, r), the shared columns scaled into r
    free = [i for i in range(p) if i not in positions]
    blocks = np.zeros((2 * n, 2 * len(free) + 2))
    for k, x in enumerate(designs):
        rows = slice(k * n, (k + 1) * n)
        blocks[rows, k * len(free) : (k + 1) * len(free)] = x[:, free]
        blocks[rows, -2:] = x[:, positions] * scales[k]
    joint = np.linalg.lstsq(blocks, np.concatenate(data), rcond=None)[0]
    joint_chi2 = float(np.sum((np.concatenate(data) - blocks @ joint) ** 2))
    np.testing.assert_allclose(r, joint[-2:], rtol=1e-9)
    np.testing.assert_allclose(cov_r, np.linalg.inv(blocks.T @ blocks)[-2:, -2:], rtol=1e-9)
    for k in range(2):
        np.testing.assert_allclose(
            shared[k][free], joint[k * len(free) : (k + 1) * len(free)], rtol=1e-9
        )
        np.testing.assert_allclose(shared[k][positions], scales[k] * r, rtol=1e-12)
    assert abs(cost - (joint_chi2 - separate)) < 1e-8 * joint_chi2
    assert cost > 0
