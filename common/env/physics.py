"""MuJoCo physics of K transport environments sharing one MjModel (no task logic here).

The high-level action of carrier i, ``a_i = [dx, dy, dpsi]`` in [-1,1]^3 and in the
carrier's own frame, moves the target of the frozen low-level tracker (position
actuators with velocity feedback on slide x, slide y, hinge yaw) to
``target_i + [R(psi_i) [dx, dy] * max_step_xy, dpsi * max_step_yaw]`` (psi_i the
measured yaw; the target stays within a leash of the measured pose), and ``substeps``
physics steps are run. The tracker is stiff: inconsistent commands strain the grasps.

The K simulations are one ``mujoco.batch.Batch`` (MuJoCo 4) run on the calling thread:
one C call steps all K, and their state is read and written in place through live
``[K, ...]`` arrays (``qpos``, ``qvel``, the tracker targets), so a step has no per-env
Python; results are bit-identical to stepping one MjData per env. Wall contact is read
from the batch too: the MJCF's contact filter lets every contact involve a wall or the
floor (checked when the model is built), so an env touches a wall iff it has more
contacts than a contact sensor on the floor counts (the sensor, added here, does not
change the dynamics).
"""
from __future__ import annotations

import copy
from collections.abc import Sequence

import mujoco
import mujoco.batch
import numpy as np

from common.env import kernels
from common.env.config import EnvConfig
from common.env.layout import CARRY_HEIGHT, GRASP_LOCAL, PAYLOAD_MASS
from common.env.mjcf import build_mjcf
from common.env.scenarios import ScenarioSpec
from common.spec import N_CARRIERS


def quat_to_yaw_tilt(quat):
    """Yaw [K] and tilt [K] (angle of the body z axis from vertical) of quaternions [K,4] (w,x,y,z)."""
    w, x, y, z = quat[:, 0], quat[:, 1], quat[:, 2], quat[:, 3]
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    zz = 1 - 2 * (x * x + y * y)  # world-z component of the body z axis
    return yaw, np.arccos(np.clip(zz, -1.0, 1.0))


def quat_rotate(quat, v):
    """Rotate body vectors v [K,P,3] by quaternions [K,4] (w,x,y,z)."""
    w = quat[:, None, :1]
    u = quat[:, None, 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def compile_model(xml: str) -> mujoco.MjModel:
    """The MJCF's model plus one contact sensor counting the floor's contacts (``sensordata[0]``).

    Raises if some pair of geoms could collide without a wall (``wall*``) or the floor in it,
    since ``wall contacts = ncon - floor contacts`` then would not hold.
    """
    spec = mujoco.MjSpec.from_string(xml)
    spec.add_sensor(type=mujoco.mjtSensor.mjSENS_CONTACT, objtype=mujoco.mjtObj.mjOBJ_GEOM, objname="floor",
                    intprm=[1, 0, 1])   # data="found": the number of matching contacts
    m = spec.compile()
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in range(m.ngeom)]
    wall_or_floor = [name.startswith("wall") or name == "floor" for name in names]
    for g1 in range(m.ngeom):
        for g2 in range(g1 + 1, m.ngeom):
            collide = (m.geom_contype[g1] & m.geom_conaffinity[g2]) or (m.geom_contype[g2] & m.geom_conaffinity[g1])
            if collide and m.geom_bodyid[g1] != m.geom_bodyid[g2] and not (wall_or_floor[g1] or wall_or_floor[g2]):
                raise ValueError(f"geoms {names[g1]!r} and {names[g2]!r} may collide: wall contact "
                                 "would be miscounted")
    if m.npair or m.nexclude:
        raise ValueError("explicit contact pairs/excludes are not supported by the wall-contact count")
    return m


def set_model_payload_mass(m: mujoco.MjModel, nominal: mujoco.MjModel, body: int, mass: float,
                           scratch: mujoco.MjData):
    """Make ``m``, a copy of the ``nominal`` model, the model compiled with a payload (body
    ``body``) of ``mass`` kg: its mass and inertia scaled (uniform density), the derived constants
    (``mj_setConst``, with ``scratch`` as its workspace) and model statistics recomputed."""
    m.body_mass[body] = mass
    m.body_inertia[body] = nominal.body_inertia[body] * (mass / PAYLOAD_MASS)
    mujoco.mj_setConst(m, scratch)
    # the compiler's model statistics (mj_setConst leaves them; the solver scales its
    # tolerance with meaninertia): mean body mass and mean diagonal inertia at qpos0
    masses, dof_m0, stat = m.body_mass, m.dof_M0, m.stat
    stat.meanmass = float(np.add.reduce(masses[1:]) / (len(masses) - 1))   # = .mean(), without its overhead
    stat.meaninertia = float(np.add.reduce(dof_m0) / len(dof_m0))


def set_model_walls(m: mujoco.MjModel, walls, wall_bodies, wall_geoms):
    """Move and resize the wall boxes ``walls [W,5]`` ``(cx, cy, hx, hy, yaw)`` of ``m`` (wall k is the
    one geom ``wall_geoms[k]`` of the static body ``wall_bodies[k]``, ``mjcf.wall_body``): the fields
    the compiler derives from a wall's pose and size (body pose, geom size, its bounding box and
    sphere, the body's one-node bounding-volume tree), so that ``m`` is the model compiled with these
    walls (tested field by field)."""
    walls = np.asarray(walls, dtype=np.float64)
    half = walls[:, 2:4]
    quat = np.zeros((len(walls), 4))
    quat[:, 0] = np.cos(walls[:, 4] / 2)
    quat[:, 3] = np.sin(walls[:, 4] / 2)
    m.body_pos[wall_bodies, :2] = walls[:, :2]
    m.body_quat[wall_bodies] = quat
    # a massless static body's inertial frame, as the compiler sets it: its body pose, and the
    # kinematics shortcut flag "same rotation as the body" (mjSAMEFRAME_BODYROT) only when unrotated
    m.body_ipos[wall_bodies] = m.body_pos[wall_bodies]
    m.body_iquat[wall_bodies] = quat
    unrotated = np.abs(quat - [1.0, 0.0, 0.0, 0.0]).max(axis=1) < 1e-14
    m.body_sameframe[wall_bodies] = np.where(unrotated, int(mujoco.mjtSameFrame.mjSAMEFRAME_BODYROT),
                                             int(mujoco.mjtSameFrame.mjSAMEFRAME_NONE))
    size = m.geom_size
    size[wall_geoms, :2] = half
    m.geom_aabb[wall_geoms, 3:5] = half    # [centre (3), half-sizes (3)] in the geom frame
    m.geom_rbound[wall_geoms] = np.sqrt((size[wall_geoms] ** 2).sum(axis=1))
    m.bvh_aabb[m.body_bvhadr[wall_bodies], 3:5] = half   # one node per wall body: its geom's box


class _DataCopies(Sequence):
    """``datas[k]``: env k's MjData at its current state, for reading and rendering: the state
    copied out of the batch into an MjData kept per env, then ``mj_forward`` for the derived
    fields (``xpos``, ``efc_force``, ...). A write to it does not reach the simulation."""

    def __init__(self, phys: TransportPhysics):
        self._phys = phys
        self._copies = [mujoco.MjData(phys.model) for _ in range(phys.K)]

    def __len__(self) -> int:
        return len(self._copies)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(len(self))[k]]
        k = range(len(self))[k]   # negative indices; IndexError past the end
        d = self._phys.batch.get_data(k, self._copies[k])
        mujoco.mj_forward(self._phys.models[k], d)
        return d


class TransportPhysics:
    """One MjModel, K simulations in one ``mujoco.batch.Batch``; the state of all K is live
    [K, ...] arrays (``qpos``, ``qvel``; ``_ctrl`` the tracker targets), written in place.

    Payload mass randomization (``set_payload_mass``) and drawn layouts (``set_walls``) need a
    per-env model, since masses and static geometry live in the MjModel: an env whose payload
    mass or walls differ from the nominal ones gets its own copy of the model (``models[k]``;
    ~30 kB), with the payload body's mass and inertia scaled (uniform density) and the derived
    constants (``mj_setConst``) recomputed, and its wall bodies moved and resized
    (:func:`set_model_walls`), as if the MJCF had been compiled with that mass and those walls
    (tested); nothing is recompiled. ``model`` stays the nominal model; the batch runs env k on
    ``models[k]``.
    """

    def __init__(self, spec: ScenarioSpec, cfg: EnvConfig, num_envs: int):
        if num_envs < 1:
            raise ValueError("num_envs must be >= 1")
        self.cfg = cfg
        self.xml = build_mjcf(spec, cfg)
        self.model = compile_model(self.xml)
        self.nominal_walls = spec.walls_array()
        W = len(self.nominal_walls)
        self.wall_bodies = np.array([mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, f"wall{w}") for w in range(W)])
        self.wall_geoms = np.array([mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, f"wall{w}") for w in range(W)])
        self._env_mass = np.full(num_envs, PAYLOAD_MASS)
        self._env_walls = np.repeat(self.nominal_walls[None], num_envs, axis=0)
        self.models = [self.model] * num_envs   # per env; a copy once its payload mass is changed
        self.K = num_envs
        # one thread (the caller's); not persistent: one MjData serves all K, which keeps it in cache
        self.batch = mujoco.batch.Batch(self.model, num_envs, nthread=1)
        self.batch.set_models(self.models)
        self.batch.reset()
        self._reset_state = self.batch.state[0].copy()   # mj_resetData's state row (the same for every mass)
        self._models_changed = False
        self._scratch = mujoco.MjData(self.model)   # mj_setConst's workspace
        self.datas = _DataCopies(self)
        m = self.model
        self.payload_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "payload")
        jid = lambda name: m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]
        self.carrier_qadr = np.array([[jid(f"c{i}_{a}") for a in ("x", "y", "yaw")] for i in range(N_CARRIERS)])
        self.carrier_vadr = np.array([[m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"c{i}_{a}")]
                                       for a in ("x", "y", "yaw")] for i in range(N_CARRIERS)])
        pj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "payload")
        self.payload_qadr, self.payload_vadr = int(m.jnt_qposadr[pj]), int(m.jnt_dofadr[pj])
        # actuator k drives carrier k//3 axis k%3 (built in that order)
        act_q = np.array([m.jnt_qposadr[m.actuator_trnid[k, 0]] for k in range(m.nu)])
        if not np.array_equal(act_q, self.carrier_qadr.reshape(-1)):
            raise RuntimeError("actuator order does not match carrier joints")
        floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
        self.is_wall = np.zeros(m.ngeom, dtype=bool)
        for g in range(m.ngeom):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
            self.is_wall[g] = name.startswith("wall")
        self.floor_id = floor
        # live views of the batch's state rows (qpos, qvel, targets, grasps on/off) and sensor outputs
        self.qpos = self.batch.bind("qpos")
        self.qvel = self.batch.bind("qvel")
        self._ctrl = self.batch.bind("ctrl")
        self._eq_active = self.batch.bind("eq_active")
        self._ncon = self.batch.bind("ncon")                 # [K] contacts at the last physics step
        self._floor_contacts = self.batch.bind("sensordata")[:, 0]
        self.contact = np.zeros(self.K, dtype=bool)
        self.released = np.zeros(self.K, dtype=bool)
        self._leash = (cfg.target_leash, cfg.target_leash * cfg.max_step_yaw / cfg.max_step_xy)

    # --- state access --------------------------------------------------------------
    def read(self):
        """Refresh ``contact``: some wall in contact at the last physics step (every contact
        involves a wall or the floor, see :func:`compile_model`)."""
        np.greater(self._ncon, self._floor_contacts, out=self.contact)

    @property
    def carrier_pose(self):
        """[K,3,3] world (x, y, yaw) of each carrier."""
        return self.qpos[:, self.carrier_qadr]

    @property
    def carrier_vel(self):
        return self.qvel[:, self.carrier_vadr]

    @property
    def payload_pos(self):
        return self.qpos[:, self.payload_qadr:self.payload_qadr + 3]

    @property
    def payload_quat(self):
        return self.qpos[:, self.payload_qadr + 3:self.payload_qadr + 7]

    @property
    def payload_vel(self):
        """[K,6] linear (world) then angular velocity."""
        return self.qvel[:, self.payload_vadr:self.payload_vadr + 6]

    def grasp_strain(self):
        """[K,3] 3-D distance between each carrier's hand anchor and its grasp point on the payload."""
        out = np.empty((self.K, N_CARRIERS))
        kernels.grasp_strain(self.payload_pos, self.payload_quat, GRASP_LOCAL, self.carrier_pose[..., :2], CARRY_HEIGHT,
                             out)
        return out

    def payload_mass(self, k: int) -> float:
        return float(self.models[k].body_mass[self.payload_body])

    def set_payload_mass(self, k: int, mass: float):
        """Give env k a payload of ``mass`` kg (mass and inertia scaled; takes effect at the next
        reset or step, call before ``reset``)."""
        self.set_episode_model(k, mass, self._env_walls[k])

    def set_walls(self, k: int, walls):
        """Give env k the walls ``[W,5]`` of a drawn layout (same count as the nominal; takes
        effect at the next reset or step, call before ``reset``)."""
        self.set_episode_model(k, self._env_mass[k], walls)

    def walls(self, k: int) -> np.ndarray:
        """Env k's walls ``[W,5]`` as its model has them."""
        return self._env_walls[k].copy()

    def set_episode_model(self, k: int, mass: float, walls):
        """Env k's model: payload ``mass`` kg and ``walls`` ``[W,5]``; the nominal mass and walls
        share the nominal model again."""
        walls = np.asarray(walls, dtype=np.float64)
        if walls.shape != self.nominal_walls.shape or not np.isfinite(walls).all() or np.any(walls[:, 2:4] <= 0):
            raise ValueError(f"walls must be finite [{len(self.nominal_walls)},5] boxes with positive half-sizes")
        self._models_changed = True
        self._env_mass[k] = mass
        moved = not np.array_equal(walls, self._env_walls[k])
        self._env_walls[k] = walls
        if mass == PAYLOAD_MASS and np.array_equal(walls, self.nominal_walls):
            self.models[k] = self.model
            return
        if self.models[k] is self.model:
            self.models[k] = copy.copy(self.model)   # MjModel copies are deep
            moved = True
        if moved:   # the same layout again (layout_spread=0) keeps its walls
            set_model_walls(self.models[k], walls, self.wall_bodies, self.wall_geoms)
        set_model_payload_mass(self.models[k], self.model, self.payload_body, mass, self._scratch)

    def _sync_models(self):
        """Hand changed per-env models to the batch (it reads them only as set)."""
        if self._models_changed:
            self.batch.set_models(self.models)
            self._models_changed = False

    # --- control --------------------------------------------------------------------
    def reset(self, envs, payload_xy, payload_yaw, carrier_pose):
        """Place envs ``envs`` (an index, or sorted distinct indices [n]): payload at (xy [n,2],
        carry height, yaw [n]), carriers at carrier_pose [n,3,3], grasps on, targets on the carriers;
        in one kernel call (``reference.physics_reset`` is the numpy computation)."""
        envs, xy, yaw, pose = self._placement(envs, payload_xy, payload_yaw, carrier_pose)
        self._sync_models()
        kernels.reset_states(envs, self._reset_state, self.batch.state, self.qpos, self._ctrl, self._eq_active,
                             self.payload_qadr, self.carrier_qadr, xy, yaw, pose, CARRY_HEIGHT)
        self.released[envs] = False
        self.contact[envs] = False

    @staticmethod
    def _placement(envs, payload_xy, payload_yaw, carrier_pose):
        """``reset``'s arguments as arrays: envs [n], xy [n,2], yaw [n], carrier poses [n,9]."""
        envs = np.atleast_1d(np.asarray(envs, dtype=np.int64))
        n = len(envs)
        return (envs, np.asarray(payload_xy, dtype=np.float64).reshape(n, 2),
                np.asarray(payload_yaw, dtype=np.float64).reshape(n),
                np.asarray(carrier_pose, dtype=np.float64).reshape(n, -1))

    def targets(self, actions):
        """Move the tracker targets (``_ctrl`` [K,9]) for stacked actions [K,9] (carrier-frame, in
        [-1,1]); ``reference.tracker_targets`` is the numpy computation
        (target integration and leash)."""
        kernels.tracker_targets(self.qpos, self.carrier_qadr, np.asarray(actions, dtype=np.float64),
                                self.cfg.max_step_xy, self.cfg.max_step_yaw, *self._leash, self._ctrl)
        return self._ctrl

    def step(self, actions):
        """Apply one control step to all K environments (one batch call) and refresh ``contact``."""
        self.targets(actions)
        self._sync_models()
        self.batch.step(nstep=self.cfg.substeps)
        self.read()

    def release(self, envs):
        """Drop: deactivate the grasp constraints of env(s) ``envs`` so the payload falls."""
        self._eq_active[envs] = 0.0
        self.released[envs] = True
