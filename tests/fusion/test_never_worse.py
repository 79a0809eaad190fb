"""The fusion never ends worse than its parts where an axis goes unobserved: the legs' bias states keep
their estimate where nothing observes them, and the gate keeps a flagged axis's ICP only where it agrees
with the legs."""

import gtsam
import numpy as np
import pytest

from fusion import BACKENDS, FusionConfig
from fusion.bias import observed_axes
from fusion.steps import gate_mask

PITCH = np.radians(2.0)  # a gentle slope, climbed
STEP = 0.1  # m a step
SIGMAS = np.array([0.004, 0.004, 0.004, 3e-4, 3e-4, 6e-4])  # the legs' per step


def rot_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def level_basis():
    """The map from a body-frame tangent onto the level frame's axes of a body pitched by PITCH."""
    R = rot_y(-PITCH)  # level from body: the body's nose is PITCH above the level plane
    return np.kron(np.eye(2), R)


def increment(x, z=0.0, yaw=0.0):
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, 0.0, z)
    return T


def walk(backend, flagged, icp_step, config, steps=400, scale=1.03, yaw_bias=0.0, held_x=40.0):
    """Climb the slope straight on: legs that over-read each step by `scale` (and turn by `yaw_bias`
    rad a metre), ICP's step `icp_step` (body frame) weighed by a Hessian that holds every axis,
    `flagged` axes (level frame) masked on every step. Returns the along-track and the across-track
    errors of the fused estimate and of the legs alone, and the fusion."""
    start = np.eye(4)
    start[:3, :3] = rot_y(-PITCH)  # nose up
    fusion = BACKENDS[backend](start, config)
    truth, legs = start.copy(), start.copy()
    odom = increment(STEP * scale, yaw=STEP * yaw_bias)
    hessian = np.diag([held_x, 400.0, 4000.0, 4000.0, 4000.0, 4000.0])  # x held less firmly than the rest
    mask = np.isin(np.arange(6), flagged)
    for _ in range(steps):
        truth = truth @ increment(STEP)
        legs = legs @ odom
        T, _ = fusion.add_step(odom, SIGMAS, icp_step, mask, hessian, 1, level_basis())

    def errors(estimate):
        off = estimate[:3, 3] - truth[:3, 3]
        along = truth[:3, 0]
        return abs(float(off @ along)), float(np.linalg.norm(off - (off @ along) * along))

    return errors(T), errors(legs), fusion


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_small_icp_height_bias_on_a_slope_does_not_move_the_strides_scale(backend):
    """x (the level frame's, along the slope) flagged on every step; ICP reads each step true but 0.4 mm
    high. The stride's scale is observed only through the step's small vertical part, which the height
    bias sets: it must keep its prior, and the walk its legs' length."""
    config = FusionConfig(odometry_bias=("yaw", "scale"))
    biased = increment(STEP, z=4e-4)
    (along, _), (legs_along, _), fusion = walk(backend, [0], biased, config)
    assert legs_along > 1.0  # 40 m at 3 % over
    assert fusion.bias_observed[1] == 0 and fusion.odometry_bias[1] == pytest.approx(0.0, abs=1e-4)
    assert along <= 1.01 * legs_along
    assert fusion.bias_observed[0] == 400  # the heading's bias is held by ICP's yaw throughout


@pytest.mark.parametrize("backend", BACKENDS)
def test_x_y_and_yaw_flagged_on_every_step_end_no_worse_than_the_legs(backend):
    config = FusionConfig(odometry_bias=("yaw", "scale"))
    (along, across), (legs_along, legs_across), fusion = walk(
        backend, [0, 1, 5], increment(STEP, z=4e-4), config, yaw_bias=0.002
    )
    assert legs_across > 0.5  # 40 m turning 2 mrad a metre
    assert (fusion.bias_observed == 0).all() and np.abs(fusion.odometry_bias).max() < 1e-4
    assert along <= 1.01 * legs_along and across <= 1.01 * legs_across


def test_a_motion_with_a_part_along_a_masked_axis_is_not_observed():
    """The marginal information: the stride of a pitched robot, along a masked level x, is not observed
    however sharply the height is held; unmasked, it is; weakly held, against the legs, it is not."""
    along = np.r_[np.zeros(3), np.cos(PITCH), 0.0, np.sin(PITCH)]  # GTSAM order: rotation, then translation
    held_height = np.diag([0.0, 1e6, 1e6, 1e6, 1e6, 1e6])  # project order: x masked
    assert not observed_axes(along[:, None], held_height, SIGMAS, 1, 0.1)[0]
    assert observed_axes(along[:, None], np.diag([1e6] * 6), SIGMAS, 1, 0.1)[0]
    assert not observed_axes(along[:, None], np.diag([100.0] + [1e6] * 5), SIGMAS, 1, 0.1)[0]
    assert not observed_axes(along[:, None], None, SIGMAS, 1, 0.1)[0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_gate_keeps_a_flagged_axis_where_icp_agrees_and_drops_a_slide(backend):
    """x flagged on every step: where ICP reads the step true (an open yard's geometry still holds it),
    the gate keeps it and the walk ends far better than the legs; where ICP stands still along x (a
    tunnel's identical rings), the gate drops it and the walk ends as the legs do. The hard mask ends as
    the legs in both."""
    gate = FusionConfig(mode="gate", odometry_bias=("yaw", "scale"))
    (true_along, _), (legs_along, _), _ = walk(backend, [0], increment(STEP), gate, steps=200, held_x=4000.0)
    (slid_along, _), _, _ = walk(backend, [0], increment(0.0), gate, steps=200, held_x=4000.0)
    hard = FusionConfig(odometry_bias=("yaw", "scale"))
    (hard_along, _), _, _ = walk(backend, [0], increment(STEP), hard, steps=200, held_x=4000.0)
    assert true_along < 0.1 * legs_along
    assert slid_along <= 1.01 * legs_along
    assert hard_along == pytest.approx(legs_along, rel=0.01)


def test_the_gate_reads_the_innovation_on_the_level_axes_against_the_legs_alone():
    basis = level_basis()
    legs = np.diag(SIGMAS**2)
    flagged = np.array([True, False, False, False, False, True])
    body_x = np.linalg.solve(basis, np.r_[0.03, np.zeros(5)])  # 3 cm along the level x, in the body frame
    assert gate_mask(flagged, basis, 0.1 * body_x, legs).tolist() == [False] * 6  # 3 mm: within 3 sigma
    assert gate_mask(flagged, basis, body_x, legs).tolist() == [True] + [False] * 5  # 3 cm: beyond
    assert not gate_mask(np.zeros(6, bool), basis, 10 * body_x, legs).any()  # nothing flagged, nothing masked


def test_gtsam_pose_order_in_the_walk_helpers():
    """The helpers' pitch is nose up: a step forward climbs."""
    T = np.eye(4)
    T[:3, :3] = rot_y(-PITCH)
    moved = T @ increment(1.0)
    assert moved[2, 3] == pytest.approx(np.sin(PITCH))
    assert gtsam.Pose3(moved).rotation().pitch() == pytest.approx(-PITCH)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_slide_that_turns_the_heading_leaves_the_heading_to_the_other_directions(backend):
    """ICP's weak direction couples the length with the heading (a gallery at an angle to the sensor's
    heading); ICP stands still along it, so each step it reads 8 cm short and turns 8 mrad. With x flagged,
    the hard mask keeps the heading's share of that slide at full weight; the gate, which still flags x,
    removes the weak direction whole and keeps the heading that the other directions hold."""
    weak = np.r_[1.0, 0.0, 0.0, 0.0, 0.0, 0.1] / np.hypot(1.0, 0.1)
    strong = np.diag([0.0, 1e3, 1e3, 1e3, 1e3, 1e3])
    strong[0, 0], strong[5, 5] = 0.0, 0.0
    across = np.r_[-0.1, 0.0, 0.0, 0.0, 0.0, 1.0] / np.hypot(1.0, 0.1)
    hessian = strong + 1e3 * np.outer(across, across) + 1e-2 * np.outer(weak, weak)
    slide = -0.08 / weak[0] * weak  # 8 cm short along the weak direction
    icp = increment(STEP + slide[0], yaw=slide[5])

    def heading_error(mode):
        fusion = BACKENDS[backend](np.eye(4), FusionConfig(mode=mode, odometry_bias=("yaw", "scale")))
        for _ in range(100):
            T, _ = fusion.add_step(increment(STEP), SIGMAS, icp, np.r_[True, np.zeros(5, bool)], hessian)
        return abs(np.arctan2(T[1, 0], T[0, 0]))

    assert heading_error("mask") > 0.3  # rad: most of the slide's 8 mrad a step
    assert heading_error("gate") < 0.01
