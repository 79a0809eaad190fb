"""The leg odometry's slowly wandering biases as states of the fusion.

Legs drift in heading and height by a rate per metre walked that persists and wanders (a random
walk per square-root metre), and their stride's length is off by a scale. With the rate (or the
scale) as a state, the ICP steps that hold yaw (z, the step's length) teach the fusion the legs'
present bias, so the legs stop pulling the heading by a fraction of their bias on every step, and
keep walking true for a while where the detector masks the scans' axes (a tunnel's length is the
legs' alone). The scale learns ICP's own step bias with it: it pays with an ICP whose steps are
true (`RegistrationConfig.ground_normals`), not with one that holds steps back beside walls
(docs/decisions.md).

Model: the measured increment M = (R, t) walked d = |t| metres; with yaw bias b_yaw (rad/m), z bias
b_z (m/m) and scale error b_s the true increment is Z(b) = (Rz(-b_yaw d) R, (1 - b_s) t - b_z d e_z).
"""

from __future__ import annotations

import gtsam
import numpy as np

from .tangent import to_project_order

BIAS_AXES = ("yaw", "z", "scale")
# The graph holds one bias state per metre walked, not one per scan: the bias wanders by
# 0.3 mrad/m over a metre, far below what a metre of ICP steps can tell, and ten times fewer
# states keep iSAM2's update near the plain graph's cost.
BIAS_KNOT_METRES = 1.0


def check_bias_axes(axes: tuple[str, ...]) -> None:
    """A ValueError unless the axes are distinct names among BIAS_AXES."""
    if any(a not in BIAS_AXES for a in axes) or len(set(axes)) != len(axes):
        raise ValueError(f"odometry_bias takes distinct axes among {BIAS_AXES}, got {tuple(axes)!r}")


def check_bias_settings(axes: tuple[str, ...], sigmas: tuple[float, ...], walk: tuple[float, ...]) -> None:
    """A ValueError naming the problem: unknown or repeated axes, or a spread or walk that is not
    a positive number (a zero walk would make the graph's tie between bias states singular)."""
    check_bias_axes(axes)
    for name, values in (("odometry_bias_sigmas", sigmas), ("odometry_bias_walk", walk)):
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (len(BIAS_AXES),) or not (np.isfinite(v).all() and (v > 0).all()):
            raise ValueError(
                f"{name} must be {len(BIAS_AXES)} positive numbers ({', '.join(BIAS_AXES)}), got {values!r}"
            )


def bias_prior(
    axes: tuple[str, ...], sigmas: tuple[float, ...], walk: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """The spread and the walk (both BIAS_AXES order) of the estimated axes, in their order."""
    pick = [BIAS_AXES.index(a) for a in axes]
    return np.asarray(sigmas, dtype=np.float64)[pick], np.asarray(walk, dtype=np.float64)[pick]


def corrected_increment(
    measured: np.ndarray, bias: np.ndarray, axes: tuple[str, ...]
) -> tuple[gtsam.Pose3, np.ndarray]:
    """Z(b) for the measured 4x4 increment, and its Jacobian G (6 x len(axes), GTSAM's
    rotation-first order) in the right perturbation: Z(b + db) = Z(b) Exp(G db)."""
    M = np.asarray(measured, dtype=np.float64)
    t = M[:3, 3]
    d = float(np.linalg.norm(t))
    rates = dict(zip(axes, np.asarray(bias, dtype=np.float64)))
    angle = -rates.get("yaw", 0.0) * d
    c, s = np.cos(angle), np.sin(angle)
    Z = np.eye(4)
    Z[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ M[:3, :3]
    Z[:3, 3] = (1.0 - rates.get("scale", 0.0)) * t - np.array([0.0, 0.0, rates.get("z", 0.0) * d])
    down = Z[:3, :3].T @ np.array([0.0, 0.0, -d])  # -d e_z seen from the corrected body frame
    G = np.zeros((6, len(axes)))
    for n, axis in enumerate(axes):
        if axis == "yaw":  # a left turn of the rotation only
            G[:3, n] = down
        elif axis == "z":  # a shift of the translation only
            G[3:, n] = down
        else:  # the step shortened along itself
            G[3:, n] = Z[:3, :3].T @ -t
    return gtsam.Pose3(Z), G


def observed_axes(
    G: np.ndarray, icp_information: np.ndarray | None, odom_sigmas: np.ndarray, span: int, share: float
) -> np.ndarray:
    """Which of a step's bias axes its registration observes: those whose motion (G's column, the
    step's change with that bias, GTSAM order) the ICP factor knows, marginally over its other
    directions, with at least `share` of the information the legs have of it over the factor's
    `span` steps. `icp_information`: the factor's 6x6 information as fused (its masked axes zero;
    project order, body frame); None where the step has no ICP factor.

    A marginal, not a conditional, information: a motion with any part along a masked axis (the stride
    of a pitched robot in a tunnel whose length is masked moves it along the tunnel and a little in
    height) is not known at all, however sharply the held part (the height) is measured. Where a bias
    were moved by such a part, ICP's small height bias on a gentle slope would set the stride's scale."""
    observed = np.zeros(G.shape[1], dtype=bool)
    if icp_information is None or not G.size:
        return observed
    w, V = np.linalg.eigh(0.5 * (icp_information + icp_information.T))
    top = float(w.max(initial=0.0))
    if top <= 0.0:
        return observed
    inverse_w = 1.0 / np.maximum(w, 1e-12 * top)  # a held-out direction: a variance beyond any motion's
    legs_variance = span * np.asarray(odom_sigmas, dtype=np.float64) ** 2
    for n in range(G.shape[1]):
        u = to_project_order(G[:, n])
        length = float(np.linalg.norm(u))
        if length == 0.0:  # standing still: the bias moves nothing
            continue
        u = u / length
        icp_variance = float(np.sum((V.T @ u) ** 2 * inverse_w))
        observed[n] = share * icp_variance <= float(np.sum(u**2 * legs_variance))
    return observed


def odometry_bias_factor(
    measured: np.ndarray,
    key_prev: int,
    key_cur: int,
    key_bias: int,
    noise: gtsam.noiseModel.Base,
    axes: tuple[str, ...],
    observed: np.ndarray | None = None,
    held: np.ndarray | None = None,
) -> gtsam.CustomFactor:
    """The leg odometry's between-factor with its bias corrected: error Log(Z(b)^-1 X_prev^-1 X_cur).
    `observed` (per axis, all where None): the axes the step's registration observes
    (`observed_axes`); the others enter as the constants `held` (their estimate when the step was
    added), so that nothing this step measures moves them.
    A Python factor because GTSAM has no between-factor whose measurement depends on another
    variable (its IMU factors model accelerometers and gyros, not legs)."""
    M = np.asarray(measured, dtype=np.float64).copy()
    live = np.ones(len(axes), dtype=bool) if observed is None else np.asarray(observed, dtype=bool).copy()
    constants = np.zeros(len(axes)) if held is None else np.asarray(held, dtype=np.float64).copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        X_prev, X_cur = values.atPose3(key_prev), values.atPose3(key_cur)
        bias = np.where(live, values.atVector(key_bias), constants)
        Z, G = corrected_increment(M, bias, axes)
        G = G * live
        E = Z.between(X_prev.between(X_cur))
        e = gtsam.Pose3.Logmap(E)
        if jacobians is not None:
            J = gtsam.Pose3.LogmapDerivative(e)
            jacobians[0] = -J @ X_cur.between(X_prev).AdjointMap()
            jacobians[1] = J
            jacobians[2] = -J @ E.inverse().AdjointMap() @ G
        return e

    return gtsam.CustomFactor(noise, [key_prev, key_cur, key_bias], error)
