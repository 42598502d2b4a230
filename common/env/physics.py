"""MuJoCo physics of K transport environments sharing one MjModel (no task logic here).

The high-level action of carrier i, ``a_i = [dx, dy, dpsi]`` in [-1,1]^3 and in the
carrier's own frame, moves the target of the frozen low-level tracker (position
actuators with velocity feedback on slide x, slide y, hinge yaw) to
``target_i + [R(psi_i) [dx, dy] * max_step_xy, dpsi * max_step_yaw]`` (psi_i the
measured yaw; the target stays within a leash of the measured pose), and ``substeps``
physics steps are run. The tracker is stiff: inconsistent commands strain the grasps.
"""
from __future__ import annotations

import copy

import mujoco
import numpy as np

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


class TransportPhysics:
    """One MjModel, K MjData; gathers the state of all K into numpy arrays.

    Payload mass randomization (``set_payload_mass``) needs a per-env model, since
    masses live in the MjModel: an env whose payload mass differs from the nominal one
    gets its own copy of the model (``models[k]``; ~30 kB), with the payload body's mass
    and inertia scaled (uniform density) and the derived constants (``mj_setConst``)
    recomputed, as if the MJCF had been compiled with that mass (tested). ``model`` stays
    the nominal model.
    """

    def __init__(self, spec: ScenarioSpec, cfg: EnvConfig, num_envs: int):
        if num_envs < 1:
            raise ValueError("num_envs must be >= 1")
        self.cfg = cfg
        self.xml = build_mjcf(spec, cfg)
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        self.datas = [mujoco.MjData(self.model) for _ in range(num_envs)]
        self.models = [self.model] * num_envs   # per env; a copy once its payload mass is changed
        self.K = num_envs
        m = self.model
        self.payload_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "payload")
        self._payload_inertia0 = m.body_inertia[self.payload_body].copy()
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
        # preallocated state buffers, refreshed by read()
        self.qpos = np.zeros((self.K, m.nq))
        self.qvel = np.zeros((self.K, m.nv))
        self.contact = np.zeros(self.K, dtype=bool)
        self.released = np.zeros(self.K, dtype=bool)
        self._grasp3 = np.concatenate([GRASP_LOCAL, np.zeros((N_CARRIERS, 1))], axis=1)[None]
        self._ctrl = np.zeros((self.K, m.nu))

    # --- state access --------------------------------------------------------------
    def read(self):
        for k, d in enumerate(self.datas):
            self.qpos[k] = d.qpos
            self.qvel[k] = d.qvel
            ncon = d.ncon
            if ncon:
                g = d.contact.geom[:ncon]
                self.contact[k] = bool(np.any(self.is_wall[g]))
            else:
                self.contact[k] = False

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
        from common.env.kernels import grasp_strain

        out = np.empty((self.K, N_CARRIERS))
        grasp_strain(self.payload_pos, self.payload_quat, GRASP_LOCAL, self.carrier_pose[..., :2], CARRY_HEIGHT, out)
        return out

    def grasp_strain_reference(self):
        """Numpy :meth:`grasp_strain` (the reference its numba kernel is tested against)."""
        grasp_w = self.payload_pos[:, None, :] + quat_rotate(self.payload_quat, np.broadcast_to(self._grasp3, (self.K, 3, 3)))
        cp = self.carrier_pose
        hand = np.concatenate([cp[..., :2], np.full((self.K, N_CARRIERS, 1), CARRY_HEIGHT)], axis=-1)
        return np.linalg.norm(grasp_w - hand, axis=-1)

    def payload_mass(self, k: int) -> float:
        return float(self.models[k].body_mass[self.payload_body])

    def set_payload_mass(self, k: int, mass: float):
        """Give env k a payload of ``mass`` kg (mass and inertia scaled; takes effect now, call
        before ``reset``). The nominal mass shares the nominal model again."""
        b = self.payload_body
        if mass == PAYLOAD_MASS:
            self.models[k] = self.model
            return
        if self.models[k] is self.model:
            self.models[k] = copy.copy(self.model)   # MjModel copies are deep
        m = self.models[k]
        m.body_mass[b] = mass
        m.body_inertia[b] = self._payload_inertia0 * (mass / PAYLOAD_MASS)
        mujoco.mj_setConst(m, self.datas[k])
        # the compiler's model statistics (mj_setConst leaves them; the solver scales its
        # tolerance with meaninertia): mean body mass and mean diagonal inertia at qpos0
        m.stat.meanmass = float(m.body_mass[1:].mean())
        m.stat.meaninertia = float(m.dof_M0.mean())

    # --- control --------------------------------------------------------------------
    def reset(self, k: int, payload_xy, payload_yaw: float, carrier_pose):
        """Place env k: payload at (xy, carry height, yaw), carriers at carrier_pose [3,3], grasps on."""
        m, d = self.models[k], self.datas[k]
        mujoco.mj_resetData(m, d)
        a = self.payload_qadr
        d.qpos[a:a + 3] = (payload_xy[0], payload_xy[1], CARRY_HEIGHT)
        d.qpos[a + 3:a + 7] = (np.cos(payload_yaw / 2), 0.0, 0.0, np.sin(payload_yaw / 2))
        d.qpos[self.carrier_qadr.reshape(-1)] = np.asarray(carrier_pose, float).reshape(-1)
        d.ctrl[:] = d.qpos[self.carrier_qadr.reshape(-1)]
        self._ctrl[k] = d.ctrl
        d.eq_active[:] = 1
        self.released[k] = False
        mujoco.mj_forward(m, d)
        self.qpos[k] = d.qpos
        self.qvel[k] = d.qvel
        self.contact[k] = False

    def targets(self, actions):
        """Tracker targets [K,9] for stacked actions [K,9] (carrier-frame, in [-1,1]).

        The target integrates the commanded displacements (so a stiff tracker holds the
        commanded formation and inconsistent commands strain the grasps) but is kept
        within ``target_leash`` of the measured pose, so a carrier blocked by a wall
        does not wind up.
        """
        cfg = self.cfg
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.K, N_CARRIERS, 3), -1.0, 1.0)
        pose = self.carrier_pose
        c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
        t = self._ctrl.reshape(self.K, N_CARRIERS, 3)
        lx, ly = cfg.target_leash, cfg.target_leash * cfg.max_step_yaw / cfg.max_step_xy
        t[..., 0] = np.clip(t[..., 0], pose[..., 0] - lx, pose[..., 0] + lx) + (c * a[..., 0] - s * a[..., 1]) * cfg.max_step_xy
        t[..., 1] = np.clip(t[..., 1], pose[..., 1] - lx, pose[..., 1] + lx) + (s * a[..., 0] + c * a[..., 1]) * cfg.max_step_xy
        t[..., 2] = np.clip(t[..., 2], pose[..., 2] - ly, pose[..., 2] + ly) + a[..., 2] * cfg.max_step_yaw
        return self._ctrl

    def step(self, actions):
        """Apply one control step to all K environments and refresh the state buffers."""
        ctrl = self.targets(actions)
        n = self.cfg.substeps
        for k, d in enumerate(self.datas):
            d.ctrl[:] = ctrl[k]
            mujoco.mj_step(self.models[k], d, n)
        self.read()

    def release(self, k: int):
        """Drop: deactivate env k's grasp constraints so the payload falls."""
        self.datas[k].eq_active[:] = 0
        self.released[k] = True
