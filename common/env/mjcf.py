"""Build the MuJoCo model (MJCF text) of a scenario.

Contact filtering (MuJoCo collides a pair when ``contype_a & conaffinity_b`` or
``contype_b & conaffinity_a`` is nonzero):

=========  =======  ===========  =========================================
geom       contype  conaffinity  collides with
=========  =======  ===========  =========================================
walls      2        0            carriers, payload
floor      4        0            payload (after a drop)
carriers   0        2            walls only (not the payload they hold)
payload    0        6            walls, floor
=========  =======  ===========  =========================================
"""
from __future__ import annotations

import math

from common.env.config import EnvConfig
from common.env.layout import CARRIER_RADIUS, CARRY_HEIGHT, GRASP_LOCAL, PAYLOAD_HALF, PAYLOAD_MASS
from common.env.scenarios import WALL_HEIGHT, ScenarioSpec
from common.spec import N_CARRIERS


def _f(*xs) -> str:
    return " ".join(repr(float(x)) for x in xs)   # shortest exact form: the model holds the very floats


def wall_body(k: int, wall) -> str:
    """Wall k, a box ``(cx, cy, hx, hy, yaw)``, as a static body of one massless geom: a body of its
    own (not a geom of the world body, whose bounding-volume tree over all its geoms the compiler
    builds once), so that a layout drawn per episode moves and resizes it in the compiled model
    (``physics.set_model_walls``) exactly as compiling this MJCF with the drawn walls would."""
    cx, cy, hx, hy, yaw = (float(v) for v in wall)
    return (f'    <body name="wall{k}" pos="{_f(cx, cy, WALL_HEIGHT / 2)}" euler="0 0 {_f(yaw)}">'
            f'<geom name="wall{k}" type="box" size="{_f(hx, hy, WALL_HEIGHT / 2)}" class="wall"/></body>')


def build_mjcf(spec: ScenarioSpec, cfg: EnvConfig, walls=None) -> str:
    """The scenario's MJCF with ``walls`` ``[W,5]`` (default: its nominal layout's)."""
    m = cfg.carrier_mass
    # critically damped tracker: kv = 2 sqrt(kp * m) (implicitfast integrates kv implicitly)
    payload_share = PAYLOAD_MASS / N_CARRIERS
    kv_xy = 2.0 * math.sqrt(cfg.kp_xy * (m + payload_share))
    i_yaw = 0.5 * m * CARRIER_RADIUS**2
    kv_yaw = 2.0 * math.sqrt(cfg.kp_yaw * i_yaw)
    walls = "\n".join(wall_body(k, w) for k, w in enumerate(spec.walls if walls is None else walls))
    carriers, actuators, equalities = [], [], []
    for i in range(N_CARRIERS):
        carriers.append(f"""
    <body name="carrier{i}">
      <joint name="c{i}_x" type="slide" axis="1 0 0"/>
      <joint name="c{i}_y" type="slide" axis="0 1 0"/>
      <joint name="c{i}_yaw" type="hinge" axis="0 0 1"/>
      <geom name="carrier{i}" type="cylinder" size="{_f(CARRIER_RADIUS, CARRY_HEIGHT / 2)}"
            pos="0 0 {CARRY_HEIGHT / 2:.6g}" mass="{m:.6g}" contype="0" conaffinity="2" rgba="0.2 0.4 0.8 1"/>
      <geom type="box" size="0.05 0.03 0.03" pos="{CARRIER_RADIUS:.6g} 0 {CARRY_HEIGHT - 0.05:.6g}"
            mass="0.01" contype="0" conaffinity="0" rgba="1 1 1 1"/>
      <site name="hand{i}" pos="0 0 {CARRY_HEIGHT:.6g}"/>
    </body>""")
        actuators += [
            f'    <position name="c{i}_x" joint="c{i}_x" kp="{cfg.kp_xy:.6g}" kv="{kv_xy:.6g}"/>',
            f'    <position name="c{i}_y" joint="c{i}_y" kp="{cfg.kp_xy:.6g}" kv="{kv_xy:.6g}"/>',
            f'    <position name="c{i}_yaw" joint="c{i}_yaw" kp="{cfg.kp_yaw:.6g}" kv="{kv_yaw:.6g}"/>',
        ]
        equalities.append(
            f'    <connect name="grasp{i}" site1="hand{i}" site2="grasp{i}" solref="{_f(*cfg.grasp_solref)}" solimp="{_f(*cfg.grasp_solimp)}"/>'
        )
    grasp_sites = "\n".join(
        f'      <site name="grasp{i}" pos="{_f(GRASP_LOCAL[i, 0], GRASP_LOCAL[i, 1], 0.0)}"/>'
        for i in range(N_CARRIERS)
    )
    hx, hy, hz = PAYLOAD_HALF
    return f"""<mujoco model="transport_{spec.name}">
  <compiler angle="radian"/>
  <option timestep="{cfg.timestep:.6g}" integrator="implicitfast" gravity="0 0 -9.81"/>
  <default>
    <default class="wall"><geom contype="2" conaffinity="0" mass="0" rgba="0.6 0.6 0.6 1"/></default>
    <geom friction="0.8 0.02 0.001"/>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="50 50 0.1" contype="4" conaffinity="0" rgba="0.9 0.9 0.9 1"/>
{walls}
{"".join(carriers)}
    <body name="payload" pos="0 0 {CARRY_HEIGHT:.6g}">
      <freejoint name="payload"/>
      <geom name="payload" type="box" size="{_f(hx, hy, hz)}" mass="{PAYLOAD_MASS:.6g}"
            contype="0" conaffinity="6" rgba="0.8 0.5 0.2 1"/>
{grasp_sites}
    </body>
  </worldbody>
  <equality>
{chr(10).join(equalities)}
  </equality>
  <actuator>
{chr(10).join(actuators)}
  </actuator>
</mujoco>
"""
