"""The skill library of the scripted experts: grasp, place, stack, insert, press, push, push_up, handover, home.

A task's `expert:` list (task.schema.json `$defs/skill`) is a short composition of these skills. Each skill is
a generator that yields *segments*, joint-mode action rows [T, 14] for the next moves, and is resumed only when
the previous segment has (nearly) been executed, so each move is planned from the state the simulator is in
then: where the block really is after it was nudged, how the grasped object really sits between the fingers.

Grasps are grounded in the assets' annotations (`grasp`, `rim`, `neck` sites; the collision box when an asset
has none), targets in placement annotations (`inside`, `hole_1`, `slot`), `top` frames and regions. Motion is
collision-aware in the simple, robust way scripted demonstrations use: approach from above, descend slowly,
close, lift clear, transfer above everything in the way, lower, release, back off along the approach;
orientations tilt forward only when a top-down gripper cannot reach (far baskets, high drops). A place that did
not land is tried again, a push is measured and corrected. `open`/`close` (drawers, doors, lids: articulated
fixtures moved by a handle) live in `dojo.experts.articulated`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Iterator
from typing import Any

import mujoco
import numpy as np

from dojo.language import skills as skill_words
from dojo.language.facts import resolve_facts

from dojo.experts.motion import (
    ARM_INDEX,
    CARRY,
    FAST,
    JOINT_SPEED,
    SLOW,
    ArmPlanner,
    Pose,
    limit_joint_speed,
)
from dojo.experts.scene import Box, Scene

Segment = np.ndarray
SkillGen = Iterator[Segment]

APPROACH = 0.08
"""Height of the pre-grasp and pre-place poses above the final pose (m)."""
CLEARANCE = 0.035
"""How far a carried object's bottom stays above everything it passes over (m)."""
MIN_TRANSFER = 0.15
"""Lowest TCP height above the table for transfers (m)."""
PALM = 0.045
"""How far below the gripper TCP an object's top may be before the palm touches it (m)."""
FINGERTIP = 0.0166
"""Fingertips below the TCP (finger length 75 mm from the mount, TCP 58.4 mm from it)."""
GRIP_STEPS = 12
THIN = 0.01
THIN_SQUEEZE = 0.003
"""Objects flatter than THIN (m) are gripped by their rim with a slow close to THIN_SQUEEZE under their width."""
THIN_AXIS = 0.35
"""An object this much thinner across one axis than across another is gripped across the thin one."""
RELEASE_STEPS = 8
SETTLE_STEPS = 4
PITCHES = (0.0, 0.35, 0.6, 0.85, 1.1, 1.35)
"""Forward tilts of the approach axis tried in turn when a top-down pose is out of reach (rad)."""
REACH_TOL = 0.004
PLACE_TRIES = 2
SETTLE_CHECK = 10
"""A place that did not land (checked like the predicates) is tried once more from where the object lies."""
PUSH_POS = 0.008
PUSH_YAW = 4.0
"""How close (m, degrees) `push` brings an object to its target frame before it stops correcting."""
CORRECT_MIN, CORRECT_MAX = 0.004, 0.08
"""A carried object found this far (m) from where it should hang above its target has its release pose
corrected (farther: something is wrong that a shift will not fix)."""
PRECISE_ABOVE = 0.01
"""Height above its goal at which an insertion measures the held object once more (m)."""
REACH = 0.5
"""Planar distance from an arm's base within which it grasps and places top-down."""
RELAY_ROOM = 0.03
"""Room (m) between a handed-over object and its neighbours that leaves space for the taker's open fingers."""
FIT_ENTER = 0.003
"""A fitted object's leading end is first pushed FIT_ENTER (m) past the opening's entrance: if it did not get in
(it stands on the rim: the aim was off by more than the play), the fit gives up (`give_up_fit`) rather than force
it: pushed on from the rim, a key slid along it into the keyway in the fingers."""
FIT_SLIP, FIT_HOLD = 0.0005, 0.0015
"""An object pushed FIT_SLIP (m) aside on its way into an opening was forced by the rim (`lowered_straight`): soft
contacts let a part pressed onto a rim sink a millimetre past it (a coin 2 mm off across a slot that gives it 0.8 mm
went in pushed aside 0.5 to 0.8 mm). One that fell FIT_HOLD (m) short of the way down was held back (a free one
lags a short push by up to 0.7 mm: the arm's own lag)."""
FIT_AIMS, FIT_AIM_TOL = 4, 0.0003
"""An inserted object's leading point found farther than FIT_AIM_TOL (m) from over the opening's centre is moved, at
most FIT_AIMS times, before it goes in."""
FIT_SETTLE = 25
"""Control steps an insertion's move is held at its end before the object is measured."""
FIT_LEAD = 0.004
"""Height (m) of an inserted object's bottom above the opening's entrance while it is aimed."""
FINGER_CLEAR = 0.002
"""Height (m) above an opening's entrance that the fingertips stop at when they lower an object through it."""
FLOOR_GAP = 0.004
"""Height (m) above what it will stand on at which an inserted object is let go."""
RELEASE_MARGIN = 0.02
"""How much wider (m) than the object an insertion opens the fingers to let go."""
PUT_BACK_DROP = 0.005
"""Height (m) above where it stood at which a part whose fit gave up is let go (it may have stood in a holder)."""


class SkillContext:
    """Commanded joint targets of both arms, the scene, and the primitives skills are written with."""

    def __init__(self, plan: Any, model: mujoco.MjModel, data: mujoco.MjData,
                 shifts: dict[str, np.ndarray] | None = None) -> None:
        self.plan, self.model, self.data = plan, model, data
        self.scene = Scene(plan, model, data, shifts)
        self.planner = ArmPlanner(model, plan.robot, plan.control_hz)
        self.planner.sync(data)
        self.max_width = float(plan.robot["gripper_max_width"])
        self.q = self.planner.index.arm_q(data).copy()
        self.grip = self.planner.index.gripper(data).copy()
        home = plan.robot["home_qpos"]
        self.home_q = np.asarray([[home[j] for j in plan.robot["arm_joints"][a * 6:(a + 1) * 6]] for a in range(2)])
        self._start_scene: Scene | None = None
        self.held: dict[int, str] = {}
        self.pitch = [0.0, 0.0]
        self.failures: list[str] = []
        self.memo: dict[Any, Any] = {}
        """What a skill measured for later steps of the same episode (the attitude a strike holds its tool in)."""

    @property
    def start_scene(self) -> Scene:
        """The scene as it was at the start of the episode (the plan's initial state)."""
        if self._start_scene is None:
            self._start_scene = Scene(self.plan, self.model, self.plan.initial_data(self.model), self.scene.shifts)
        return self._start_scene

    # ---- segments ----

    def rows(self, path: list[np.ndarray], grips: list[np.ndarray] | None = None) -> Segment:
        """Action rows for joint targets `path` [T][2, J] (grippers held unless given per row)."""
        out = np.empty((len(path), 14), np.float32)
        for k, q in enumerate(path):
            grip = self.grip if grips is None else grips[k]
            out[k] = np.concatenate([q[0], [grip[0]], q[1], [grip[1]]])
        if path:
            self.q = path[-1].copy()
        if grips:
            self.grip = grips[-1].copy()
        return out

    def hold(self, steps: int) -> Segment:
        return self.rows([self.q.copy()] * steps)

    def gripper(self, arm: int, value: float, steps: int) -> Segment:
        grip = self.grip.copy()
        grip[arm] = value
        return self.rows([self.q.copy()] * steps, [grip] * steps)

    def gripper_ramp(self, arm: int, start: float, end: float, steps: int) -> Segment:
        """The gripper command moved linearly from `start` to `end` over `steps` (a slow close)."""
        grips = []
        for k in range(1, steps + 1):
            grip = self.grip.copy()
            grip[arm] = start + (end - start) * min(1.0, k / max(1, steps - 4))
            grips.append(grip)
        return self.rows([self.q.copy()] * steps, grips)

    def line(self, arm: int, goal: Pose, speed: float, settle: int = SETTLE_STEPS) -> Segment:
        path = self.planner.line(self.q, arm, goal, speed, seed=self._seed(arm, goal.pos))
        return self.rows(path + [path[-1]] * settle)

    def joints(self, arm: int, q_goal: np.ndarray) -> Segment:
        """A joint-space move of one arm (going home: no Cartesian path is needed in free space above)."""
        goal = self.q.copy()
        goal[arm] = q_goal
        return self.rows(limit_joint_speed(self.q, [goal], JOINT_SPEED * self.planner.dt) + [goal] * SETTLE_STEPS)

    def tcp(self, arm: int) -> Pose:
        return self.planner.fk(self.q, arm)

    def actual_tcp(self, arm: int) -> np.ndarray:
        return self.data.site_xpos[self.planner.index.ee_sites[arm]].copy()

    def actual_tcp_rot(self, arm: int) -> np.ndarray:
        return self.data.site_xmat[self.planner.index.ee_sites[arm]].reshape(3, 3).copy()

    # ---- orientations and reach ----

    def reach_dir(self, arm: int, point: np.ndarray) -> np.ndarray:
        d = point[:2] - self.planner.base_pos[arm, :2]
        d = d / max(float(np.linalg.norm(d)), 1e-6)
        return np.array([d[0], d[1], 0.0])

    def natural_axis(self, arm: int, point: np.ndarray) -> np.ndarray:
        """The finger axis of a top-down grasp with an unrolled wrist: horizontal, across the reach direction."""
        return np.cross(self.reach_dir(arm, point), [0.0, 0.0, -1.0])

    def orientation(self, arm: int, point: np.ndarray, axis: np.ndarray, pitch: float) -> np.ndarray:
        """Gripper rotation with the approach axis tilted `pitch` forward from straight down, fingers closing
        along `axis` (projected perpendicular to the approach)."""
        u = self.reach_dir(arm, point)
        approach = math.cos(pitch) * np.array([0.0, 0.0, -1.0]) + math.sin(pitch) * u
        f = axis - np.dot(axis, approach) * approach
        f = f / np.linalg.norm(f)
        return np.column_stack([approach, f, np.cross(approach, f)])

    def reachable(self, arm: int, point: np.ndarray, axis: np.ndarray, prefer: float = 0.0) -> Pose:
        """The least tilted pose at `point` that the arm reaches, trying the tilt `prefer` first (a carried
        object keeps the tilt it was grasped with); the closest one if none is exact."""
        return self.reachable_with(arm, lambda pitch: Pose(point.copy(), self.orientation(arm, point, axis, pitch)),
                                   prefer)

    def reachable_with(self, arm: int, make_pose: Any, prefer: float = 0.0) -> Pose:
        """`reachable` for poses that depend on the tilt: `make_pose(pitch)` (a held object's offset from the
        TCP turns with the gripper)."""
        best, best_err = None, np.inf
        for pitch in [prefer, *(p for p in PITCHES if p > prefer)]:
            pose = make_pose(pitch)
            _, err = self.planner.ik(self._seed(arm, pose.pos), arm, pose)
            if err < REACH_TOL:
                self.pitch[arm] = pitch
                return pose
            if err < best_err:
                best, best_err = pose, err
        return best

    def highest(self, arm: int, pose: Pose, low: float, high: float) -> float:
        """The highest TCP height in [low, high] above `pose`'s point that the arm reaches without changing the
        gripper's orientation (a carried object then keeps its attitude); `low` if none is reachable."""
        for z in np.linspace(high, low, 6):
            _, err = self.planner.ik(self._seed(arm, pose.pos), arm, Pose(np.array([*pose.pos[:2], z]), pose.rot))
            if err < REACH_TOL:
                return float(z)
        return low

    def _seed(self, arm: int, point: np.ndarray) -> np.ndarray:
        """An IK seed facing the point: home pose with the base joint turned towards it."""
        seed = self.q.copy()
        q = self.home_q[arm].copy()
        u = self.reach_dir(arm, point)
        base_x = self.planner.base_rot[arm][:, 0]
        q[0] = math.atan2(base_x[0] * u[1] - base_x[1] * u[0], float(np.dot(base_x[:2], u[:2])))
        seed[arm] = np.clip(q, self.planner.lo[arm], self.planner.hi[arm])
        return seed

    def choose_arm(self, arm: str, *points: np.ndarray) -> int:
        """`left`/`right`, or for `auto` the arm whose base is nearer the farthest of `points`."""
        if arm != "auto":
            return ARM_INDEX[arm]
        far = [max(float(np.linalg.norm(p[:2] - self.planner.base_pos[a, :2])) for p in points) for a in range(2)]
        return int(np.argmin(far))

    def transfer_height(self, exclude: tuple[str, ...], start: np.ndarray, goal: np.ndarray, below_tcp: float,
                        container: str | None = None) -> float:
        """TCP height for moving from `start` to `goal` (world points): the carried part (`below_tcp` under the
        TCP) clears by CLEARANCE every object within reach of the straight path; a target container counts with
        its rim (`top` frame), since the object goes in past its handle or lid, not over it, unless the goal
        lies across the handle from the start (the near side was taken): then it is carried over the handle."""
        tops = [self.scene.table_z]
        for name in self.scene.others(exclude):
            box = self.scene.box(name)
            if _distance_to_segment(box.center[:2], start[:2], goal[:2]) > float(np.max(box.half[:2])) + 0.08:
                continue
            if name == container and self.scene.has_site(name, "top") and all(
                    _same_side(b, start[:2], goal[:2]) for b in overhead_parts(self, name)):
                tops.append(float(self.scene.site(name, "top").center[2]))
            else:
                tops.append(box.top)
        return max(self.scene.table_z + MIN_TRANSFER, max(tops) + CLEARANCE + below_tcp)


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-9), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


# ---- grasping ----

def grasp_frame(ctx: SkillContext, obj: str) -> tuple[Box, np.ndarray]:
    """The region to grasp (an annotation box, else the object's box) and the candidate finger axes: the first
    annotation that top-down fingers reach below the palm (a tall bottle's middle is out of their reach and
    grasping just above it closes on the sloping shoulder, which slips out: its neck is taken instead)."""
    box = ctx.scene.box(obj)
    names = [a for a in ("grasp", "rim", "neck") if ctx.scene.has_site(obj, a)]
    reached = [a for a in names if _top(ctx.scene.site(obj, a)) >= box.top - PALM]
    for annotation in reached[:1] or names[:1]:
        site = ctx.scene.site(obj, annotation)
        if annotation == "rim":
            return site, np.asarray([site.center - box.center])
        return Box(site.center, box.rot, np.maximum(site.half, 1e-3)), box.rot[:, :2].T
    return box, box.rot[:, :2].T


def _top(region: Box) -> float:
    return float(region.center[2] + np.abs(region.rot[2]) @ region.half)


def finger_axis(ctx: SkillContext, arm: int, obj: str, region: Box, axes: np.ndarray) -> tuple[np.ndarray, float]:
    """The horizontal finger axis to close along and the opening needed: among the object's horizontal axes
    along which the object fits between the fingers at the grasp point, the one nearest the unrolled wrist
    (rim grasps close across the rim)."""
    natural = ctx.natural_axis(arm, region.center)
    candidates = []
    for axis in axes:
        axis = np.array([axis[0], axis[1], 0.0])
        if np.linalg.norm(axis) < 1e-6:
            continue
        axis = axis / np.linalg.norm(axis)
        # across what is between the fingers at the grasp point (a T's stem, not the whole T)
        width = ctx.scene.width_through(obj, region.center, axis) if len(axes) > 1 else 0.01
        candidates.append((axis, width))
    widest = max(w for _, w in candidates)
    best = None
    for axis, width in candidates:
        fits = width < ctx.max_width - 0.012
        thin = width < THIN_AXIS * widest  # a coin on edge is pinched across its faces, never across its rim
        key = (fits, thin, abs(float(np.dot(axis, natural))) if fits else -width)
        if best is None or key > best[0]:
            best = (key, axis if np.dot(axis, natural) >= 0 else -axis, width)
    assert best is not None
    return best[1], best[2]


def grasp_height(ctx: SkillContext, obj: str) -> float:
    """The TCP height of a top-down grasp of `obj`: at its grasp region, no lower than its top allows the palm
    and than the fingertips clear what it stands on."""
    region, axes = grasp_frame(ctx, obj)
    box = ctx.scene.box(obj)
    support = box.bottom  # fingertips just above what the object stands on (flat things: a coin)
    z = max(float(region.center[2]), box.top - PALM, support + FINGERTIP + min(0.003, 0.15 * (box.top - support)))
    if len(axes) > 1:  # fingertips no lower than the grasp region (a coin standing in a holder's groove)
        z = max(z, float(region.center[2] - region.half[2]) + FINGERTIP)
    return z


def grasp(ctx: SkillContext, arm: int, obj: str, attempts: int = 3, pitch: float = 0.0, upright: bool = False
          ) -> SkillGen:
    """Pick `obj` from above: pre-grasp, open just wide enough, descend, close, lift clear of the table. The
    gripper tilts `pitch` forward (or more, if the arm does not reach it so), for a drop that needs the tilt.
    `upright` (an insertion): a round object is gripped across the reach direction, so that the tilt turns the
    gripper about the finger axis and the object stays upright between the pads (across another axis, the pads
    lean and a test tube leans with them)."""
    for _ in range(attempts):
        region, axes = grasp_frame(ctx, obj)
        box = ctx.scene.box(obj)
        if box.bottom < ctx.scene.table_z - 0.05 or float(np.linalg.norm(
                box.center[:2] - ctx.planner.base_pos[arm, :2])) > 2.0 * REACH:
            raise SkillFailed(f"{obj} is off the table or out of reach")
        start_center = float(box.center[2])
        axis, width = finger_axis(ctx, arm, obj, region, axes)
        if upright and ctx.scene.upright_round(obj):
            axis = ctx.natural_axis(arm, region.center)
        point = np.array([*region.center[:2], grasp_height(ctx, obj)])
        pose = ctx.reachable(arm, point, axis, prefer=pitch)
        opening = min(1.0, (width + 0.03) / ctx.max_width)
        above = pose.shifted([0.0, 0.0, APPROACH])
        yield ctx.gripper(arm, opening, 1)
        yield ctx.line(arm, above, FAST)
        yield ctx.line(arm, pose, SLOW)
        if box.top - box.bottom < THIN:
            # a coin: close slowly and squeeze gently (a hard squeeze presses the pads' edges past its thin
            # rim, onto its face), so that the pads hold it by the rim
            gentle = max(0.0, (width - THIN_SQUEEZE) / ctx.max_width)
            yield ctx.gripper_ramp(arm, opening, gentle, 2 * GRIP_STEPS)
        else:
            yield ctx.gripper(arm, 0.0, GRIP_STEPS)
        yield ctx.line(arm, pose.shifted([0.0, 0.0, APPROACH]), SLOW)
        if ctx.scene.box(obj).center[2] > start_center + 0.5 * APPROACH:
            ctx.held[arm] = obj
            return
        yield ctx.gripper(arm, 1.0, RELEASE_STEPS)
    raise SkillFailed(f"could not grasp {obj}")


class SkillFailed(RuntimeError):
    """A skill gave up (the expert then holds still; the episode ends at its horizon, unsolved)."""


def _rotate_z(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


# ---- carrying and putting down ----

def carry_to(ctx: SkillContext, arm: int, obj: str, goal_center: np.ndarray, yaw_change: float = 0.0,
             release: bool = True, speed_down: float = SLOW, container: str | None = None,
             precise: bool = False) -> SkillGen:
    """Move the held `obj` so that its box centre reaches `goal_center`: up to a safe height, across, down,
    then open and retreat. `yaw_change` turns the object about world z on the way (push_t). `precise`
    (insertions) measures and corrects the object's position once more just above the goal, to a millimetre."""
    box = ctx.scene.box(obj)
    tcp = ctx.actual_tcp(arm)
    # where the object sits in the gripper's frame, as grasped: it turns with the gripper (a new tilt or yaw
    # swings a tall object's centre round the TCP)
    local = ctx.actual_tcp_rot(arm).T @ (box.center - tcp)
    below = float(tcp[2] - box.bottom)
    safe = ctx.transfer_height((obj,), box.center, goal_center, below, container)
    axis = _rotate_z(ctx.tcp(arm).rot[:, 1], yaw_change)  # the object turns with the fingers, by yaw_change
    if ctx.pitch[arm] > 0.0 and yaw_change == 0.0:
        axis = _follow_reach(ctx, arm, axis, tcp, goal_center)
    axis[2] = 0.0
    if yaw_change == 0.0 and np.dot(axis, ctx.natural_axis(arm, goal_center)) < 0.0:
        axis = -axis  # the same grasp turned half round: the wrist stays inside its range

    # the object's corners in the gripper's frame: dropped into a container, its lowest corner in the attitude
    # of the release stays as far above the rim as the planned drop asks (a tall bottle held by its top and
    # tilted to reach over a high rim hangs lower than it stood)
    corners = ctx.actual_tcp_rot(arm).T @ (_corners(box) - tcp).T
    drop = float(goal_center[2] - (box.center[2] - box.bottom))

    opening = ctx.scene.site(container, "inside") if container and ctx.scene.has_site(container, "inside") else None

    def holding(pitch: float) -> Pose:
        rot = ctx.orientation(arm, goal_center, axis, pitch)
        centre = goal_center.copy()
        if container is not None:
            hanging = rot @ corners - (rot @ local)[:, None]  # corners round the object's centre [3, 8]
            centre[2] = drop + float(-np.min(hanging[2]))
            if opening is not None:
                centre[:2] += _fit_over(opening, centre, hanging)
        return Pose(centre - rot @ local, rot)

    pose = ctx.reachable_with(arm, holding, prefer=ctx.pitch[arm])
    here = ctx.tcp(arm)
    under = ctx.scene.highest_top((obj,), goal_center, float(np.max(box.half[:2])))
    floor = max(pose.pos[2] + 0.02, under + 0.01 + below)
    if safe > floor:  # no higher than the arm reaches at both ends with the object's attitude unchanged
        safe = max(floor, min(safe, ctx.highest(arm, here, min(here.pos[2], safe), safe),
                              ctx.highest(arm, pose, floor, safe)))
    if here.pos[2] < safe:
        yield ctx.line(arm, Pose(np.array([*here.pos[:2], safe]), here.rot), CARRY, settle=0)
    above = Pose(np.array([*pose.pos[:2], max(safe, pose.pos[2])]), pose.rot)
    outside = _outside_rim(ctx, arm, container, obj, here.pos, above.pos) if container else None
    if outside is not None and above.pos[2] <= min(safe, here.pos[2]) + 0.005:
        outside = None  # the object already clears the rim: in and out from above, as for any target
    if outside is not None:
        # the arm could not lift the object over the rim where it picked it up (a tall bottle hangs far below
        # the fingers): it climbs the rest of the way outside the rim and goes in level, where a rising
        # diagonal would drag the object across the rim and shove the container
        yield ctx.line(arm, Pose(np.array([*outside, above.pos[2]]), above.rot), CARRY, settle=0)
    yield ctx.line(arm, above, CARRY, settle=8)
    # where the object really hangs now (a heavy one turns in the fingers when the gripper tilts): correct
    # the release pose by what it is off, measured above the target, before going down
    error = goal_center + [0.0, 0.0, above.pos[2] - pose.pos[2]] - ctx.scene.box(obj).center
    if CORRECT_MIN < float(np.linalg.norm(error[:2])) < CORRECT_MAX:
        pose = pose.shifted([error[0], error[1], 0.0])
        yield ctx.line(arm, above.shifted([error[0], error[1], 0.0]), SLOW, settle=6)
    if precise:
        near = pose.shifted([0.0, 0.0, PRECISE_ABOVE])
        yield ctx.line(arm, near, speed_down, settle=10)
        error = goal_center + [0.0, 0.0, PRECISE_ABOVE] - ctx.scene.box(obj).center
        if float(np.linalg.norm(error[:2])) < CORRECT_MAX:
            pose = pose.shifted([error[0], error[1], 0.0])
            yield ctx.line(arm, near.shifted([error[0], error[1], 0.0]), SLOW / 2, settle=10)
    yield ctx.line(arm, pose, speed_down)
    if release:
        yield from open_and_retreat(ctx, arm)
        if outside is not None:  # back out over the rim level: a joint move home from inside would sweep it
            back = ctx.tcp(arm)
            yield ctx.line(arm, Pose(np.array([*outside, max(back.pos[2], above.pos[2])]), back.rot), FAST, settle=0)


def _outside_rim(ctx: SkillContext, arm: int, container: str, obj: str, start: np.ndarray, goal: np.ndarray
                 ) -> np.ndarray | None:
    """The TCP's last point (xy) on the straight way from `start` to `goal` where the held object, as it hangs
    round the TCP (a tilted bottle's bottom leads), is still clear of the container's footprint by CLEARANCE;
    None if the way starts within that distance."""
    tcp = ctx.actual_tcp(arm)
    hang = float(np.max(np.linalg.norm(_corners(ctx.scene.box(obj))[:, :2] - tcp[:2], axis=1)))
    bin_box = ctx.scene.box(container)
    radius = float(np.max(bin_box.half[:2])) + hang + CLEARANCE
    centre, a, d = bin_box.center[:2], start[:2], goal[:2] - start[:2]
    # |a + t d - centre| = radius: the smaller root is where the way enters the circle
    f = a - centre
    qa, qb, qc = float(d @ d), 2.0 * float(f @ d), float(f @ f) - radius ** 2
    if qc <= 0.0 or qa < 1e-9 or qb * qb - 4.0 * qa * qc < 0.0:
        return None
    t = (-qb - math.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)
    return a + t * d if 0.0 < t < 1.0 else None


def _fit_over(opening: Box, centre: np.ndarray, hanging: np.ndarray) -> np.ndarray:
    """The least planar shift of a dropped object's centre that brings its footprint (corner offsets `hanging`
    [3, 8] round `centre`) over the opening; the footprint centred on the opening when it is wider (a bottle
    tilted to reach over a high rim, whose ends would come down on the rim)."""
    axes = opening.rot[:2, :2]
    local = axes.T @ (centre[:2] - opening.center[:2])
    lo, hi = local + np.min(axes.T @ hanging[:2], axis=1), local + np.max(axes.T @ hanging[:2], axis=1)
    half = opening.half[:2]
    shift = np.where(hi - lo > 2.0 * half, -(lo + hi) / 2.0, np.clip(0.0, -half - lo, half - hi))
    return axes @ shift


def _corners(box: Box) -> np.ndarray:
    """The eight corners [8, 3] of a box in the world."""
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
    return box.center + signs @ (box.rot * box.half).T


def open_and_retreat(ctx: SkillContext, arm: int, opening: float = 1.0) -> SkillGen:
    """Let go and back out along the approach axis (straight up for a top-down gripper; a tilted one backs
    off the object instead of dragging it along between the open fingers). `opening` (a share of the widest):
    fingers among close neighbours (tubes in a rack) open only so far."""
    yield ctx.gripper(arm, opening, RELEASE_STEPS)
    ctx.held.pop(arm, None)
    here = ctx.tcp(arm)
    yield ctx.line(arm, here.shifted(-APPROACH * here.rot[:, 0]), FAST, settle=0)


def pushed_in(ctx: SkillContext, arm: int, lead: Callable[[], np.ndarray], entrance: float, speed: float
              ) -> Generator[Segment, None, bool]:
    """Push the held object down until its leading point (`lead()`: where it is now) is FIT_ENTER past an
    opening's `entrance` (a height); whether it got in straight (`lowered_straight`): a point on the rim stays at
    the entrance, one let in off its aim by a chamfer or a tilt in the fingers was pushed aside on the way."""
    down = float(lead()[2]) - (entrance - FIT_ENTER)
    straight = yield from lowered_straight(ctx, arm, lead, -down, speed)
    return straight and float(lead()[2]) < entrance - FIT_ENTER / 2


def lowered_straight(ctx: SkillContext, arm: int, lead: Callable[[], np.ndarray], dz: float, speed: float
                     ) -> Generator[Segment, None, bool]:
    """Move the held object `dz` (m) down the way it was aimed (straight down); whether its leading point (`lead()`)
    went so, neither pushed aside (FIT_SLIP) nor held back (FIT_HOLD) by a rim: a rounded end let in a few
    millimetres off, then cammed along the rim into a hole that it fits only with a millimetre of play, was forced
    in, as a careful robot does not do."""
    start = lead()
    yield ctx.line(arm, ctx.tcp(arm).shifted([0.0, 0.0, dz]), speed, settle=FIT_SETTLE)
    moved = lead() - start
    return float(np.linalg.norm(moved[:2])) < FIT_SLIP and float(moved[2]) - dz < FIT_HOLD


def leading_point(ctx: SkillContext, obj: str) -> np.ndarray:
    """The centre of an object's bottom face, the end that goes into an opening first (it swings aside most when
    the object is pushed over on its way in)."""
    box = ctx.scene.box(obj)
    return box.center - box.rot[:, 2] * box.half[2]


def give_up_fit(ctx: SkillContext, arm: int, obj: str, target: str) -> SkillGen:
    """A fit whose object did not go in straight (`pushed_in`, `lowered_straight`): lift it back out and set it
    down where it stood when the episode began, then fail. Not let go over the opening: released there, gravity
    and the opening's chamfers would fit it for the robot (a charger plugged 3 mm off and let go by the next step,
    `home`, fell into its socket)."""
    yield from carry_to(ctx, arm, obj, ctx.start_scene.box(obj).center + [0.0, 0.0, PUT_BACK_DROP])
    raise SkillFailed(f"{obj} did not enter {target}; put back")


def place_center(ctx: SkillContext, arm: int, obj: str, target: str) -> np.ndarray:
    """Where the box centre of `obj` goes for `target`: resting on a surface (a region spot, an object's top, a
    placement annotation) or, for a container, released above its rim at the point of its opening nearest the
    arm (easiest to reach), on the side of a handle over the middle that the object comes from (an object off a
    belt behind a basket is not carried across the handle) and clear of it, to drop in."""
    box = ctx.scene.box(obj)
    height = float(np.abs(box.rot[2]) @ box.half)
    if target in ctx.plan.regions:
        spot = ctx.scene.region_spot(target, obj, clearance=2.0 * float(np.max(box.half[:2])) + 0.02)
        return spot + [0.0, 0.0, height + 0.006]
    if _covers(ctx, obj, target):  # a cover goes over the target, down to the target's own support
        under = ctx.scene.box(target)
        return np.array([*under.center[:2], under.bottom + height + 0.004])
    goal = ctx.scene.target(target)
    if not goal.container:
        return goal.point + [0.0, 0.0, height + 0.006]
    owner = target.split("/", 1)[0]
    site = ctx.scene.site(owner, target.split("/", 1)[1])
    size = float(np.max(box.half[:2]))
    base = ctx.planner.base_pos[arm, :2]
    inside = [ctx.scene.box(n) for n in ctx.scene.others((obj, owner))
              if np.all(np.abs(site.rot.T @ (ctx.scene.box(n).center - site.center)) <= site.half + 0.02)]
    floor = float(site.center[2] - site.half[2]) + 0.01
    walls = [b for b in ctx.scene.geom_boxes(owner) if b.top > floor]  # walls, posts, a handle: not the floor
    overhead = overhead_parts(ctx, owner)

    def near(xy: np.ndarray) -> bool:
        """On the side of a handle (its narrow axis) the object comes from, else in the half of the opening
        facing the arm: an object carried across the handle would sweep into it."""
        if overhead:
            return all(_same_side(b, xy, box.center[:2]) for b in overhead)
        return float(np.dot(xy - site.center[:2], base - site.center[:2])) >= 0.0

    def grid(span: np.ndarray, n: int) -> list[np.ndarray]:
        return [site.center[:2] + site.rot[:2, :2] @ (span * [u, v]) for u in np.linspace(-1, 1, n)
                for v in np.linspace(-1, 1, n)]

    def room(xy: np.ndarray) -> float:
        return min((_footprint_distance(xy, b) for b in walls), default=np.inf) - size

    def key(xy: np.ndarray, per_metre: float = 100.0) -> tuple[bool, float, float]:
        free = all(np.linalg.norm(xy - b.center[:2]) > size + float(np.max(b.half[:2])) + 0.01 for b in inside)
        # room to every wall and the handle, in whole centimetres (`per_metre`) up to the object's size: a
        # dropped object lands clear of the rim (it tips over a wall it lands next to) and of a handle it would hit
        return (not free, -round(min(room(xy), size) * per_metre), float(np.linalg.norm(xy - base)))

    spots = [xy for xy in grid(np.maximum(site.half[:2] - size - 0.01, 0.0), 5) if near(xy)]
    if all(key(xy)[0] for xy in spots):
        # the near half is taken (bottles standing in a bin): anywhere over the opening that keeps the object's
        # centre in the placement box, rather than onto what stands there (never across a handle: the carry
        # would sweep into it)
        spots = [xy for xy in grid(np.maximum(site.half[:2] - 0.01, 0.0), 7) if not overhead or near(xy)] or grid(
            np.maximum(site.half[:2] - 0.01, 0.0), 7)  # a container knocked over: no side faces the arm
    xy = min(spots, key=key)
    if room(xy) < 0.0:
        # nowhere a centimetre from the walls clears them and the handle too (an apple beside a basket's
        # handle: coming down over it, it is caught between the fingers and the handle, and the basket is
        # lifted with it): the spot of the near side with the most room, to the millimetre (then the nearest
        # the arm: the first of two objects goes to the end of the strip, leaving room for the second), however
        # close to a wall, since a dropped object falls straight past it
        fine = [xy for xy in grid(np.maximum(site.half[:2] - 0.005, 0.0), 13) if near(xy)]
        best = min(fine or [xy], key=lambda p: key(p, per_metre=1000.0))
        if key(best)[0] == key(xy)[0] and room(best) > room(xy) + 0.002:
            xy = best
    return np.array([xy[0], xy[1], max(float(site.center[2]), _rim(ctx, owner) + 0.015) + height])


def _rim(ctx: SkillContext, owner: str) -> float:
    """Height of a container's rim: its `top` frame, else the top of its box."""
    return float(ctx.scene.site(owner, "top").center[2]) if ctx.scene.has_site(owner, "top") else ctx.scene.box(
        owner).top


def overhead_parts(ctx: SkillContext, owner: str) -> list[Box]:
    """The parts of a container above its rim (a handle arching over the opening), as world boxes."""
    rim = _rim(ctx, owner)
    return [b for b in ctx.scene.geom_boxes(owner) if b.bottom > rim + 0.01]


def _same_side(box: Box, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether planar points `a` and `b` lie on the same side of a box along its narrow horizontal axis."""
    k = int(np.argmin(box.half[:2]))
    axis = box.rot[:2, k]
    return float(np.dot(a - box.center[:2], axis)) * float(np.dot(b - box.center[:2], axis)) >= 0.0


def _footprint_distance(xy: np.ndarray, box: Box) -> float:
    """Planar distance from a point to a box's footprint (zero inside it; boxes turned about z only)."""
    local = box.rot.T @ np.array([xy[0] - box.center[0], xy[1] - box.center[1], 0.0])
    return float(np.linalg.norm(np.maximum(np.abs(local[:2]) - box.half[:2], 0.0)))


def _covers(ctx: SkillContext, obj: str, target: str) -> bool:
    """Whether placing `obj` at object `target` means covering it: `obj` has an `inside` space the target fits."""
    if target not in ctx.plan.objects or not ctx.scene.has_site(obj, "inside"):
        return False
    inner, under = ctx.scene.site(obj, "inside"), ctx.scene.box(target)
    return bool(np.all(under.half < inner.half))


def place(ctx: SkillContext, arm: str, obj: str, target: str) -> SkillGen:
    """Pick `obj` and put it at `target`; with `auto`, when no arm reaches both, hand it over (`relay`)."""
    owner = target.split("/", 1)[0] if "/" in target else None
    here, goal = ctx.scene.box(obj).center, ctx.scene.target(target).point
    a = ctx.choose_arm(arm, here, goal)
    if arm == "auto" and not (_within_reach(ctx, a, here) and _reaches_target(ctx, a, obj, target)):
        near_goal = [float(np.linalg.norm(goal[:2] - ctx.planner.base_pos[k, :2])) for k in range(2)]
        if abs(near_goal[0] - near_goal[1]) > 0.02:
            a = int(np.argmin(near_goal))  # else (a target midway) the arm nearer the object keeps it
        if not _within_reach(ctx, a, here):
            yield from relay(ctx, 1 - a, obj, a)
    for _ in range(PLACE_TRIES):
        yield from free_other_arm(ctx, a)
        pitch = upright_pitch(ctx, a, obj, place_center(ctx, a, obj, target), owner)
        yield from grasp(ctx, a, obj, pitch=pitch)
        yield from carry_to(ctx, a, obj, place_center(ctx, a, obj, target), container=owner)
        yield ctx.hold(SETTLE_CHECK)  # a dropped object has landed before it is judged
        if placed(ctx, obj, target):
            return
        a = ctx.choose_arm(arm, ctx.scene.box(obj).center, goal)


def upright_pitch(ctx: SkillContext, arm: int, obj: str, goal: np.ndarray, container: str | None = None
                  ) -> float:
    """The gripper tilt to grasp an object with for carrying it from where it stands to `goal`: the least tilt
    at which the arm holds it upright with its bottom clear of everything in the way, at both ends. A
    top-down gripper does not reach so high beyond ~0.4 m from the arm's base: a cup carried as high as it
    reaches sweeps into the covers it passes, and a tall bottle (grasped top-down, it hangs from its top)
    tilted on the way leans out, into the bottles it passes and across a bin's rim. Grasped tilted, the
    object hangs upright, passes over and drops in bottom first. Zero when top-down reaches, or no tilt does,
    and for squat objects other than covers set down outside a container."""
    if not _tall(ctx.scene.box(obj)) and (container is not None or not ctx.scene.has_site(obj, "inside")):
        return 0.0  # a block's edges, a fruit's curve slip in tilted fingers: only covers' bands are held tilted
    return next((pitch for pitch in PITCHES if carries_over(ctx, arm, obj, goal, container, pitch)), 0.0)


def _tall(box: Box) -> bool:
    """Whether an object stands at least twice as tall as it is wide (it hangs from a top-down grasp)."""
    return float(np.abs(box.rot[2]) @ box.half) >= 2.0 * float(np.max(np.abs(box.rot[:2]) @ box.half))


def insert_pitch(ctx: SkillContext, arm: int, obj: str, above: np.ndarray) -> float:
    """The gripper tilt to grasp an object with for inserting it, its centre brought to `above` the opening: the
    tilt that carries it upright (`upright_pitch`) or, for a tall one, the least tilt at which the arm holds it
    upright there if that is more (low over a far opening a top-down arm falls short; grasped upright and tilted
    there, a test tube would lean in its hole)."""
    pitch = upright_pitch(ctx, arm, obj, above)
    box = ctx.scene.box(obj)
    if not _tall(box):
        return pitch
    point = above + [0.0, 0.0, grasp_height(ctx, obj) - float(box.center[2])]
    axis = ctx.natural_axis(arm, point)
    return next((p for p in PITCHES if p >= pitch and ctx.planner.ik(
        ctx._seed(arm, point), arm, Pose(point, ctx.orientation(arm, point, axis, p)))[1] < REACH_TOL), pitch)


def carries_over(ctx: SkillContext, arm: int, obj: str, goal: np.ndarray, container: str | None = None,
                 pitch: float = 0.0) -> bool:
    """Whether the arm, gripping `obj` with the tilt `pitch`, holds it high enough above both ends of the way
    to `goal` for its bottom to clear everything in the way (the carry goes no higher than the arm reaches
    there: lower, it sweeps what stands between)."""
    box = ctx.scene.box(obj)
    region, axes = grasp_frame(ctx, obj)
    axis = finger_axis(ctx, arm, obj, region, axes)[0]
    # a little higher than the bare need: the carry measures the grasp as it came out
    need = ctx.transfer_height((obj,), box.center, goal, grasp_height(ctx, obj) - box.bottom, container) + 0.02
    start, end = np.array([*region.center[:2], need]), np.array([goal[0], goal[1], need])
    turned = _follow_reach(ctx, arm, axis, start, end)
    return all(ctx.planner.ik(ctx._seed(arm, p), arm, Pose(p, ctx.orientation(arm, p, a, pitch)))[1] < REACH_TOL
               for p, a in ((start, axis), (end, turned)))


def _follow_reach(ctx: SkillContext, arm: int, axis: np.ndarray, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """The finger axis `axis` at `start` turned about the vertical as the arm's reach direction turns from
    `start` to `goal`: a gripper tilted towards its reach keeps its tilt towards the new reach direction, and
    the object it holds then turns about the vertical only (kept fixed, the fingers would roll the gripper,
    and a bottle grasped tilted would be set down on its edge and fall)."""
    before, after = ctx.reach_dir(arm, start), ctx.reach_dir(arm, goal)
    return _rotate_z(axis, math.atan2(before[0] * after[1] - before[1] * after[0], float(before @ after)))


def placed(ctx: SkillContext, obj: str, target: str) -> bool:
    """Whether `obj` ended where `target` asks, the way the task predicates look at it: inside a placement
    box, over a covered object, or resting at a surface point or in a region."""
    box = ctx.scene.box(obj)
    if _covers(ctx, obj, target):
        inner = ctx.scene.site(obj, "inside")
        return bool(np.all(np.abs(inner.rot.T @ (ctx.scene.box(target).center - inner.center)) <= inner.half + 0.005))
    goal = ctx.scene.target(target)
    if goal.container or target in ctx.plan.regions:
        owner = ctx.scene.site(*target.split("/", 1)) if goal.container else None
        rot = owner.rot if owner is not None else np.eye(3)
        centre = owner.center if owner is not None else goal.point + [0.0, 0.0, 0.15]
        half = goal.half if owner is not None else goal.half + [0.0, 0.0, 0.15]
        return bool(np.all(np.abs(rot.T @ (box.center - centre)) <= half + 0.005))
    return bool(np.linalg.norm(box.center[:2] - goal.point[:2]) < 0.02 and abs(box.bottom - goal.point[2]) < 0.02)


def relay(ctx: SkillContext, giver: int, obj: str, taker: int) -> SkillGen:
    """Hand `obj` from one arm to the other through the table: the giver sets it down at the free spot
    between the arms nearest the taker that it carries the object to over everything in the way, where both
    reach it top-down."""
    yield from free_other_arm(ctx, giver)
    box = ctx.scene.box(obj)
    size = float(np.max(box.half[:2]))
    bases = ctx.planner.base_pos[:, :2]
    spots = [np.array([x, y]) for x in np.linspace(-0.12, 0.12, 7) for y in np.linspace(-0.22, -0.02, 5)]
    others = [ctx.scene.box(n) for n in ctx.scene.others((obj,))]

    def clearance(xy: np.ndarray) -> float:
        return min((float(np.linalg.norm(xy - b.center[:2])) - size - float(np.max(b.half[:2])) for b in others),
                   default=np.inf)

    height = float(np.abs(box.rot[2]) @ box.half)

    def goal(xy: np.ndarray) -> np.ndarray:
        return np.array([xy[0], xy[1], ctx.scene.table_z + height + 0.006])

    def key(xy: np.ndarray) -> tuple[float, float]:
        # every free spot alike, then the nearest the taker; when none is free, the one with the most room
        return (-min(clearance(xy), RELAY_ROOM), float(np.linalg.norm(xy - bases[taker])))

    def carried(xy: np.ndarray) -> bool:
        # near its base, the giver cannot lift the object over a can it passes on the way: it would sweep it
        if ctx.transfer_height((obj,), box.center, goal(xy), grasp_height(ctx, obj) - box.bottom) <= (
                ctx.scene.table_z + MIN_TRANSFER):
            return True  # nothing in the way stands higher than every carry goes
        return carries_over(ctx, giver, obj, goal(xy), pitch=upright_pitch(ctx, giver, obj, goal(xy)))

    xy = next((p for p in sorted(spots, key=key) if clearance(p) >= RELAY_ROOM and carried(p)), None)
    if xy is None:
        # the objects stand between the arms: the table in front of them, nearer the bases, too (both arms
        # reach it top-down); set down beside a neighbour, the taker's open fingers would land on it
        front = [np.array([x, y]) for x in np.linspace(-0.12, 0.12, 7) for y in np.linspace(-0.34, -0.26, 3)]
        ranked = sorted(spots + front, key=key)
        xy = next((p for p in ranked if carried(p)), ranked[0])
    yield from grasp(ctx, giver, obj, pitch=upright_pitch(ctx, giver, obj, goal(xy)))
    yield from carry_to(ctx, giver, obj, goal(xy))


def stack(ctx: SkillContext, arm: str, obj: str, target: str) -> SkillGen:
    yield from place(ctx, arm, obj, target)


def insert(ctx: SkillContext, arm: str, obj: str, target: str) -> SkillGen:
    """Put `obj` into a hole or slot (`object/annotation`: a box from the entrance, its top, to its bottom): grasp
    unless held, carry it over the opening with its bottom just above the entrance (measured and corrected on the
    way down), push it a few millimetres in and, once it is in, lower it slowly until its bottom is near the
    opening's floor or its fingertips near the entrance (at least FIT_ENTER in) and let go. An object that does
    not enter, or goes in only pushed aside or held back by the rim, is put back (`give_up_fit`)."""
    if "/" not in target:
        raise SkillFailed(f"insert: target {target!r} is not an object/annotation opening")
    goal = ctx.scene.target(target)
    box = ctx.scene.box(obj)
    entrance = float(goal.point[2] + 2.0 * goal.half[2])
    above = np.array([*goal.point[:2], entrance + FIT_LEAD + float(np.abs(box.rot[2]) @ box.half)])
    a = next((k for k, held in ctx.held.items() if held == obj), None)
    if a is None:  # a tall object (a test tube) is grasped with the tilt that brings it upright over the opening
        a = ctx.choose_arm(arm, box.center, goal.point)
        yield from free_other_arm(ctx, a)
        yield from grasp(ctx, a, obj, pitch=insert_pitch(ctx, a, obj, above), upright=True)
    yield from carry_to(ctx, a, obj, above, yaw_change=_slot_yaw(ctx, obj, target), release=False,
                        speed_down=SLOW / 2, precise=True)
    for _ in range(FIT_AIMS):  # the end that goes in first over the opening's centre (a held tube leans a little)
        error = goal.point[:2] - leading_point(ctx, obj)[:2]
        if float(np.linalg.norm(error)) < FIT_AIM_TOL:
            break
        yield ctx.line(a, ctx.tcp(a).shifted([error[0], error[1], 0.0]), SLOW / 4, settle=10)
    if not (yield from pushed_in(ctx, a, lambda: leading_point(ctx, obj), entrance, SLOW / 2)):
        yield from give_up_fit(ctx, a, obj, target)
    # down to just above what it will stand on (a rack's base) or, through a slot in a lid, as far as the
    # fingers clear the lid
    floor = ctx.scene.floor_under(target.split("/", 1)[0], np.array([*goal.point[:2], entrance]))
    fingers = float(ctx.tcp(a).pos[2]) - FINGERTIP - (entrance + FINGER_CLEAR)
    bottom = min(max(floor + FLOOR_GAP, ctx.scene.box(obj).bottom - fingers), entrance - FIT_ENTER)
    if not (yield from lowered_straight(ctx, a, lambda: leading_point(ctx, obj), bottom - ctx.scene.box(obj).bottom,
                                        SLOW / 2)):
        yield from give_up_fit(ctx, a, obj, target)
    # let go no wider than the object and a margin: a finger opened wide would knock a neighbour over
    yield from open_and_retreat(ctx, a, min(1.0, (2.0 * float(np.max(box.half[:2])) + RELEASE_MARGIN) / ctx.max_width))


def _slot_yaw(ctx: SkillContext, obj: str, target: str) -> float:
    """The turn about z that lines a thin object's thin axis up with a slot's narrow axis (a coin on edge into a
    coin bank); zero unless the target is an elongated opening and the object is thin."""
    if "/" not in target:
        return 0.0
    site = ctx.scene.site(*target.split("/", 1))
    if np.min(site.half[:2]) <= 0.0 or np.max(site.half[:2]) < 2.0 * np.min(site.half[:2]):
        return 0.0
    narrow = site.rot[:, int(np.argmin(site.half[:2]))]
    box = ctx.scene.box(obj)
    flat = [k for k in range(3) if abs(box.rot[2, k]) < 0.5]  # the object's horizontal axes
    if len(flat) < 2:
        return 0.0
    thin, wide = sorted(flat, key=lambda k: box.half[k])[:2]
    if box.half[thin] > THIN_AXIS * box.half[wide]:
        return 0.0
    t = box.rot[:, thin]
    angle = math.atan2(t[0] * narrow[1] - t[1] * narrow[0], t[0] * narrow[0] + t[1] * narrow[1])
    return _wrap(2.0 * angle) / 2.0  # an axis, not a direction: within a quarter turn


def press(ctx: SkillContext, arm: str, obj: str, times: int = 1) -> SkillGen:
    """Press a button's interaction point with the closed fingertips, then come back up; `times` times (the cap
    springs back up between presses, far enough to count each one)."""
    annotation = "pressed" if ctx.scene.has_site(obj, "pressed") else "top"
    point = ctx.scene.site(obj, annotation).center
    a = ctx.choose_arm(arm, point)
    yield from free_other_arm(ctx, a)
    yield ctx.gripper(a, 0.0, 4)
    tcp = point + [0.0, 0.0, FINGERTIP]
    pose = ctx.reachable(a, tcp, ctx.natural_axis(a, tcp))
    yield ctx.line(a, pose.shifted([0.0, 0.0, APPROACH]), FAST)
    for _ in range(times):
        yield ctx.line(a, pose.shifted([0.0, 0.0, -0.011]), SLOW / 2, settle=6)
        yield ctx.line(a, pose.shifted([0.0, 0.0, APPROACH]), FAST)


def push_up(ctx: SkillContext, arm: str, obj: str, height: float) -> SkillGen:
    """Lift the object held (grasping it first if needed) to `height` above the table."""
    a = next((k for k, held in ctx.held.items() if held == obj), None)
    if a is None:
        a = ctx.choose_arm(arm, ctx.scene.box(obj).center)
        yield from grasp(ctx, a, obj)
    here = ctx.tcp(a)
    box = ctx.scene.box(obj)
    lift = max(0.0, ctx.scene.table_z + height + 0.02 - box.bottom)
    # near its base a top-down arm lifts only ~12 cm above the table, and a tall object is held by its top:
    # the gripper then tilts forward (the object hangs no lower for it) or also reaches outwards, as far as
    # it needs to get that high
    goal = here.shifted([0.0, 0.0, lift])
    out, axis = ctx.reach_dir(a, here.pos), here.rot[:, 1]
    reaches = iter(np.linspace(0.0, 0.2, 5))
    while (ctx.planner.ik(ctx._seed(a, goal.pos), a, goal)[1] >= REACH_TOL
           and (reach := next(reaches, None)) is not None):
        goal = ctx.reachable(a, here.pos + [reach * out[0], reach * out[1], lift], axis)
    yield ctx.line(a, goal, SLOW, settle=10)


def push(ctx: SkillContext, arm: str, obj: str, target: str, tries: int = 3, at_start: bool = False) -> SkillGen:
    """Bring `obj` onto a target frame with its heading (push_T's outcome): grasp it, carry it over, turn it
    to the target's yaw on the way, set it down; then measure and correct, up to `tries` times in all, until
    it lies within PUSH_POS / PUSH_YAW of the target (the first long carry is the least precise). `at_start`:
    the target frame as it was at the start of the episode (swap_T: where the other T lay), which the expert
    saw then as the robot did."""
    scene = ctx.start_scene if at_start else ctx.scene
    goal = scene.site(*target.split("/", 1)) if "/" in target else scene.box(target)
    for _ in range(tries):
        box = ctx.scene.box(obj)
        ref = ctx.scene.site(obj, "center").center if ctx.scene.has_site(obj, "center") else box.center
        turn = _wrap(_yaw(goal.rot) - _yaw(box.rot))
        if np.linalg.norm(ref[:2] - goal.center[:2]) < PUSH_POS and abs(turn) < math.radians(PUSH_YAW):
            return
        a = ctx.choose_arm(arm, box.center, goal.center)
        if arm == "auto" and not (_within_reach(ctx, a, box.center) and _within_reach(ctx, a, goal.center)):
            # no arm reaches both: the one nearer the target takes it, the other one handing it over first
            a = int(np.argmin([np.linalg.norm(goal.center[:2] - ctx.planner.base_pos[k, :2]) for k in range(2)]))
            bases = ctx.planner.base_pos[:, :2]
            if not _within_reach(ctx, a, box.center) and (
                    np.linalg.norm(box.center[:2] - bases[1 - a]) < np.linalg.norm(box.center[:2] - bases[a])):
                yield from relay(ctx, 1 - a, obj, a)
        yield from free_other_arm(ctx, a)
        yield from grasp(ctx, a, obj)
        box = ctx.scene.box(obj)
        ref = ctx.scene.site(obj, "center").center if ctx.scene.has_site(obj, "center") else box.center
        turn = _wrap(_yaw(goal.rot) - _yaw(box.rot))
        shift = _rotate_z(box.center - ref, turn)
        yield from carry_to(ctx, a, obj, np.array([goal.center[0] + shift[0], goal.center[1] + shift[1],
                                                   box.center[2]]), yaw_change=turn)


def handover(ctx: SkillContext, arm: str, obj: str, target: str) -> SkillGen:
    """Bring `obj` to `target` with the arm that reaches the target, the other arm handing it over first when
    the object lies out of that arm's reach (`place` with `auto` does exactly this)."""
    yield from place(ctx, "auto", obj, target)


def _reaches_target(ctx: SkillContext, arm: int, obj: str, target: str) -> bool:
    """Whether `arm` can put `obj` at `target` without a handover: the target is within top-down reach, or
    the arm reaches the release pose there with some forward tilt (a container's opening a little beyond
    REACH is dropped into from above)."""
    goal = ctx.scene.target(target)
    if _within_reach(ctx, arm, goal.point) or not goal.container:
        return _within_reach(ctx, arm, goal.point)  # a stack or a surface spot wants a top-down gripper
    box = ctx.scene.box(obj)
    point = place_center(ctx, arm, obj, target) + [0.0, 0.0, max(0.0, box.top - float(box.center[2]) - PALM)]
    axis = ctx.natural_axis(arm, point)
    seed = ctx._seed(arm, point)
    return any(ctx.planner.ik(seed, arm, Pose(point, ctx.orientation(arm, point, axis, pitch)))[1] < REACH_TOL
               for pitch in PITCHES)


def _within_reach(ctx: SkillContext, arm: int, point: np.ndarray) -> bool:
    """Whether `arm` reaches `point` with a top-down gripper near the table (measured: about 0.5 m)."""
    return float(np.linalg.norm(point[:2] - ctx.planner.base_pos[arm, :2])) < REACH


def home(ctx: SkillContext) -> SkillGen:
    for a in range(2):
        yield from retreat(ctx, a)
    q = ctx.home_q
    goal = ctx.q.copy()
    goal[:] = q
    path = limit_joint_speed(ctx.q, [goal], JOINT_SPEED * ctx.planner.dt)
    yield ctx.rows(path + [goal] * SETTLE_STEPS, [np.ones(2)] * (len(path) + SETTLE_STEPS))


def retreat(ctx: SkillContext, arm: int) -> SkillGen:
    """Lift an arm that is low over the table, so that it can swing away without touching anything: its
    fingertips also clear the tops of the objects beside it (a gripper that let go of a bottle's neck with a
    tilt backs off beside the bottle, at the height of the bottles' tops)."""
    here = ctx.tcp(arm)
    beside = ctx.scene.highest_top(tuple(ctx.held.values()), here.pos, 0.1)
    floor = max(ctx.scene.table_z + MIN_TRANSFER, beside + CLEARANCE + FINGERTIP)
    if here.pos[2] < floor:
        yield ctx.line(arm, Pose(np.array([*here.pos[:2], floor]), here.rot), FAST, settle=0)


def free_other_arm(ctx: SkillContext, arm: int) -> SkillGen:
    """Send the other arm home if it is away from it, so that it does not stand over the working arm's
    objects (arms do not collide with each other, but a low arm would sweep the table)."""
    other = 1 - arm
    if other in ctx.held or np.max(np.abs(ctx.q[other] - ctx.home_q[other])) < 0.05:
        return
    yield from retreat(ctx, other)
    yield ctx.joints(other, ctx.home_q[other])


def _yaw(rot: np.ndarray) -> float:
    return math.atan2(rot[1, 0], rot[0, 0])


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


# ---- programs ----

def expand(plan: Any, steps: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The expert's steps with `for_each` groups expanded (`_` replaced by each member, in name order) and facts
    (`{attribute: [card, number]}`) replaced by this episode's values."""
    out = []
    for step in resolve_facts(steps, plan.objects):
        group = step.get("for_each")
        if not group:
            out.append(step)
            continue
        members = sorted(n for n, o in plan.objects.items() if o.get("group") == group)
        for member in members:
            out.append({k: (v.replace("_", member, 1) if isinstance(v, str) and v.split("/")[0] == "_" else v)
                        for k, v in step.items() if k != "for_each"})
    return out


def run_skill(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    """The generator of one expert step, from its word's runner (`dojo.language.skills`)."""
    word = skill_words.word(step["skill"])
    if word is None:
        raise ValueError(f"skill {step['skill']!r} is not a skill word (known: {', '.join(skill_words.names())})")
    return word.runner()(ctx, step)


# Runners of the built-in skill words: a step's fields to the skill's arguments.
def run_place(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return place(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"))


def run_stack(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return stack(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"))


def run_grasp(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return grasp(ctx, ctx.choose_arm(step.get("arm", "auto"), ctx.scene.box(step["object"]).center), step["object"])


def run_insert(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return insert(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"))


def run_press(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return press(ctx, step.get("arm", "auto"), step.get("object"), int(step.get("times", 1)))


def run_push_up(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return push_up(ctx, step.get("arm", "auto"), step.get("object"), float(step.get("height", 0.1)))


def run_push(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return push(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"),
                at_start=step.get("target_at", "now") == "start")


def run_handover(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return handover(ctx, step.get("arm", "auto"), step.get("object"), step.get("target"))


def run_release(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    obj = step.get("object")
    return open_and_retreat(ctx, ctx.choose_arm(step.get("arm", "auto"), ctx.scene.box(obj).center) if obj else 0)


def run_home(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return home(ctx)


def run_wait(ctx: SkillContext, step: dict[str, Any]) -> SkillGen:
    return iter([ctx.hold(int(step.get("steps", 10)))])


def program(ctx: SkillContext, steps: list[dict[str, Any]]) -> SkillGen:
    """Every step of an expert in turn; a step that gives up is skipped (its failures are kept in
    `ctx.failures`), since later steps may still score stages."""
    for step in expand(ctx.plan, steps):
        try:
            yield from run_skill(ctx, step)
        except SkillFailed as err:
            ctx.failures.append(str(err))
