"""Video of one deployed episode (``sage eval --video``): the shield's correction made visible.

``VideoRecorder`` is a deployment recorder (``common.evaluation.deployment.DeploymentRecorder``):
the deployment loop hands it every step, so the video shows the very episode that is scored,
with no second copy of the deployment step. Each frame is a scene view plus an overlay:

* the scene: ``camera``, MuJoCo's offscreen renderer from a free camera tracking the payload
  (needs OpenGL: EGL when headless), or ``topdown``, a 2-D Pillow drawing of walls, route,
  goal, payload and carriers that needs no GL;
* on the scene, per carrier, the proposed command a_ST of the trees (magenta arrow) and the
  command a_exec the exact QP executed (black arrow), in the world frame;
* a panel below: per carrier its leaf, both commands in the carrier's own frame (dx, dy arrow,
  dyaw bar) and ||a_exec - a_ST||; a header with the step, the joint leaf tuple, the team's
  ||a_exec - a_ST|| and the active QP rows; the last frame adds the episode's outcome.

MP4 is written with imageio's ffmpeg plugin (imageio-ffmpeg bundles the binary), GIF with
Pillow; both are the optional ``video`` extra, imported only when a video is written.
"""
from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.env.layout import CARRIER_RADIUS, CARRY_HEIGHT, PAYLOAD_HALF
from common.spec import CARRIER_ACT_DIM, N_CARRIERS

VIEWS = ("camera", "topdown")
SUFFIXES = (".mp4", ".gif")
EXTRA_HINT = "pip install -e '.[video]'"

PROPOSED = (190, 30, 170)    # magenta: the trees' a_ST
EXECUTED = (20, 20, 20)      # black: the QP's a_exec
CARRIER = (50, 100, 200)     # the MJCF's colours, so both views read alike
PAYLOAD = (205, 128, 50)
WALL = (110, 110, 110)
GOAL = (40, 160, 70)
ROUTE = (120, 190, 130)
FLOOR = (232, 232, 232)
ALERT = (190, 0, 0)          # the outcome line, the correction bars
ARROW_GAIN = 6.0             # world arrows: a full step (max_step_xy = 0.08 m) drawn 0.48 m long


@dataclass(frozen=True)
class VideoConfig:
    """What to render: ``view`` (``VIEWS``), which episode (its env index in the deployment
    batch), frame ``width`` in pixels (rounded to a multiple of 16 for the codecs), one frame
    every ``every`` steps, ``fps`` (None: real time, 1 / (control_dt * every)) and how long
    the outcome frame is held."""

    view: str = "topdown"
    episode: int = 0
    width: int = 480
    every: int = 1
    fps: float | None = None
    hold_s: float = 1.0

    def __post_init__(self) -> None:
        if self.view not in VIEWS:
            raise ValueError(f"video view must be one of {VIEWS}, got {self.view!r}")
        if self.episode < 0 or self.every < 1 or self.hold_s < 0:
            raise ValueError("video: episode >= 0, every >= 1 and hold_s >= 0 required")
        if not 160 <= self.width <= 640:   # 640: MuJoCo's default offscreen buffer width
            raise ValueError(f"video width must be in [160, 640] pixels, got {self.width}")
        if self.fps is not None and self.fps <= 0:
            raise ValueError(f"video fps must be > 0, got {self.fps}")


def frame_size(width: int) -> tuple[int, int, int]:
    """(width, scene height, panel height), each a multiple of 16 (H.264 macro blocks)."""
    w = 16 * round(width / 16)
    return w, 16 * round(0.6 * w / 16), 16 * round(0.3 * w / 16)


def missing_dependency(suffix: str) -> str | None:
    """The first package of the ``video`` extra that writing a ``suffix`` file lacks, or None."""
    need = ["PIL"] + (["imageio", "imageio_ffmpeg"] if suffix == ".mp4" else [])
    for name in need:
        try:
            module = __import__(name)
        except ImportError:
            return {"PIL": "pillow", "imageio_ffmpeg": "imageio-ffmpeg"}.get(name, name)
        if name == "imageio_ffmpeg":
            try:
                module.get_ffmpeg_exe()
            except RuntimeError:
                return "imageio-ffmpeg (its bundled ffmpeg binary)"
    return None


# ------------------------------------------------------------------ OpenGL
_GL_PROBE_XML = "<mujoco><worldbody><geom type='sphere' size='0.1'/></worldbody></mujoco>"


def _context_class(backend: str):
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    elif backend == "glfw":
        from mujoco.glfw import GLContext
    else:
        raise ValueError(f"MUJOCO_GL={backend} is not an offscreen backend (egl, osmesa, glfw)")
    return GLContext


@functools.cache
def _gl_context_class():
    """(GLContext class, None) for the first offscreen backend that renders here, or (None, why not).

    The backends tried are ``MUJOCO_GL`` if set, else EGL, then GLFW where there is a display.
    They are chosen here rather than through ``mujoco.Renderer``, whose backend is fixed when
    mujoco is first imported (by the env, long before a video is asked for). The probe makes a
    context and a MuJoCo render context on it: some backends (GLFW without a reachable display)
    only fail there."""
    import mujoco

    chosen = os.environ.get("MUJOCO_GL", "").lower()
    backends = [chosen] if chosen else ["egl"] + (["glfw"] if os.environ.get("DISPLAY") else [])
    why = []
    for backend in backends:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")   # GLFW warns before it fails
                context_class = _context_class(backend)
                ctx = context_class(16, 16)
                ctx.make_current()
                mujoco.MjrContext(mujoco.MjModel.from_xml_string(_GL_PROBE_XML),
                                  mujoco.mjtFontScale.mjFONTSCALE_100).free()
                ctx.free()
            return context_class, None
        except Exception as exc:   # any failure (no libEGL, no device, no display) means: not this one
            text = str(exc).strip().splitlines()
            why.append(f"{backend}: {text[0] if text else type(exc).__name__}")
    return None, "; ".join(why)


def gl_unavailable() -> str | None:
    """Why the ``camera`` view cannot render here (one line), or None when OpenGL works."""
    return _gl_context_class()[1]


# ------------------------------------------------------------------ one step's data
@dataclass
class StepView:
    """What a frame shows of env ``k`` at one step (world frame, metres, radians)."""

    step: int
    limit: int
    carrier_xy: np.ndarray   # [N, 2]
    carrier_yaw: np.ndarray  # [N]
    payload_xy: np.ndarray   # [2]
    payload_yaw: float
    goal_xy: np.ndarray      # [2]
    a_st: np.ndarray         # [N, 3] proposed (trees; the human's own block where held)
    a_exec: np.ndarray       # [N, 3] executed (exact QP)
    leaf: np.ndarray         # [N]
    active_rows: int
    human_slot: int | None
    max_step_xy: float

    @classmethod
    def of(cls, env, k: int, decision: dict, a_exec: np.ndarray, active: np.ndarray) -> "StepView":
        snap = env.snap
        return cls(step=int(env.t[k]), limit=int(env.max_steps), carrier_xy=np.array(snap.cxy[k], np.float64),
                   carrier_yaw=np.array(snap.cyaw[k], np.float64), payload_xy=np.array(snap.pxy[k], np.float64),
                   payload_yaw=float(snap.pyaw[k]), goal_xy=np.array(env.goal_xy[k], np.float64),
                   a_st=np.asarray(decision["a_st"][k], np.float64).reshape(N_CARRIERS, CARRIER_ACT_DIM),
                   a_exec=np.asarray(a_exec[k], np.float64).reshape(N_CARRIERS, CARRIER_ACT_DIM),
                   leaf=np.asarray(decision["leaf"][k]).astype(int), active_rows=int(np.sum(active[k])),
                   human_slot=env.cfg.human_slot, max_step_xy=float(env.cfg.max_step_xy))

    def world_step(self, a: np.ndarray) -> np.ndarray:
        """[N, 2] world-frame displacement of commands ``a`` [N, 3] (own frame, as the physics applies them)."""
        c, s = np.cos(self.carrier_yaw), np.sin(self.carrier_yaw)
        return np.stack([c * a[:, 0] - s * a[:, 1], s * a[:, 0] + c * a[:, 1]], axis=1) * self.max_step_xy

    @property
    def leaf_tuple(self) -> str:
        """``(3, 7, 1)``; a human-held slot shows ``h`` (its tree's leaf drives nothing)."""
        return "(" + ", ".join("h" if i == self.human_slot else str(int(v)) for i, v in enumerate(self.leaf)) + ")"

    @property
    def correction(self) -> np.ndarray:
        """[N] ||a_exec - a_ST|| per carrier (0 on a human-held block: the QP never moves it)."""
        return np.linalg.norm(self.a_exec - self.a_st, axis=1)


# ------------------------------------------------------------------ drawing helpers
def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:   # Pillow < 10.1: one fixed-size bitmap font
        return ImageFont.load_default()


def _arrow(draw, p0, p1, colour, width: int) -> None:
    """A line p0 -> p1 (pixels) with a filled head; nothing for a zero-length arrow."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    n = float(np.hypot(*d))
    if n < 1.0:
        return
    u, v = d / n, np.array([-d[1], d[0]]) / n
    head = min(3.0 * width + 4.0, 0.6 * n)
    base = p1 - u * head
    draw.line([tuple(p0), tuple(base)], fill=colour, width=width)
    draw.polygon([tuple(p1), tuple(base + v * head * 0.5), tuple(base - v * head * 0.5)], fill=colour)


def _box_corners(cx, cy, hx, hy, yaw) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return corners @ np.array([[c, s], [-s, c]]) + [cx, cy]


# ------------------------------------------------------------------ scene views
class TopDownView:
    """2-D scene (Pillow, no GL): the whole scenario within its plot bounds."""

    def __init__(self, spec, route_points: np.ndarray, width: int, height: int, walls=None):
        """``walls`` [W,5]: the episode's layout (default: the spec's nominal walls)."""
        from PIL import Image, ImageDraw

        self.w, self.h = width, height
        x0, x1, y0, y1 = spec.bounds
        walls = spec.walls if walls is None else walls
        if len(walls):   # a drawn layout may reach past the nominal plot extent
            pts = np.concatenate([_box_corners(*w) for w in walls])
            x0, y0 = np.minimum([x0, y0], pts.min(axis=0) - 0.1)
            x1, y1 = np.maximum([x1, y1], pts.max(axis=0) + 0.1)
        self.scale = min((width - 8) / (x1 - x0), (height - 8) / (y1 - y0))
        self.origin = np.array([0.5 * (width - self.scale * (x1 + x0)), 0.5 * (height + self.scale * (y1 + y0))])
        # walls and route never move: drawn once
        self.background = Image.new("RGB", (width, height), FLOOR)
        draw = ImageDraw.Draw(self.background)
        for wall in walls:
            draw.polygon([tuple(p) for p in self.px(_box_corners(*wall))], fill=WALL)
        draw.line([tuple(p) for p in self.px(route_points)], fill=ROUTE, width=1)

    def px(self, xy) -> np.ndarray:
        """World (x, y) -> pixel (column, row); y points up."""
        xy = np.asarray(xy, np.float64)
        return np.stack([self.origin[0] + self.scale * xy[..., 0], self.origin[1] - self.scale * xy[..., 1]], axis=-1)

    def render(self, env, k: int, view: StepView) -> np.ndarray:
        from PIL import ImageDraw

        img = self.background.copy()
        draw = ImageDraw.Draw(img)
        g, r = self.px(view.goal_xy), max(3.0, 0.12 * self.scale)
        draw.ellipse([g[0] - r, g[1] - r, g[0] + r, g[1] + r], outline=GOAL, width=2)
        corners = _box_corners(*view.payload_xy, PAYLOAD_HALF[0], PAYLOAD_HALF[1], view.payload_yaw)
        draw.polygon([tuple(p) for p in self.px(corners)], fill=PAYLOAD, outline=(120, 70, 20))
        rc = CARRIER_RADIUS * self.scale
        lw = max(2, self.w // 200)
        for i in range(N_CARRIERS):
            c = self.px(view.carrier_xy[i])
            human = view.human_slot == i
            draw.ellipse([c[0] - rc, c[1] - rc, c[0] + rc, c[1] + rc], outline=(150, 80, 20) if human else CARRIER,
                         width=lw)
            heading = view.carrier_xy[i] + CARRIER_RADIUS * np.array([math.cos(view.carrier_yaw[i]),
                                                                      math.sin(view.carrier_yaw[i])])
            draw.line([tuple(c), tuple(self.px(heading))], fill=CARRIER, width=1)
        # the proposal wider and underneath: where the QP left it unchanged it shows as a rim
        for a, colour, width in ((view.a_st, PROPOSED, lw + 3), (view.a_exec, EXECUTED, lw)):
            tips = view.carrier_xy + ARROW_GAIN * view.world_step(a)
            for i in range(N_CARRIERS):
                _arrow(draw, self.px(view.carrier_xy[i]), self.px(tips[i]), colour, width)
        return np.asarray(img)


class CameraView:
    """MuJoCo offscreen render from a free camera whose look-at point follows the payload.

    Uses the low-level renderer (MjvScene, MjrContext, mjr_render) with the GL context of
    ``_gl_context_class`` (see there why not ``mujoco.Renderer``); adds the goal and the
    proposed/executed arrows to the scene as decoration geoms, leaving the model untouched."""

    DISTANCE, ELEVATION, AZIMUTH = 6.0, -60.0, 90.0   # from the -y side, the route running left to right
    HEADLIGHT = (0.45, 0.75)                          # ambient, diffuse: the model's own headlight is dim

    def __init__(self, model, width: int, height: int):
        import mujoco

        context_class, why = _gl_context_class()
        if context_class is None:
            raise RuntimeError(f"no OpenGL for the camera view ({why})")
        self._mj = mujoco
        self.w, self.h = width, height
        self.gl = context_class(width, height)
        self.gl.make_current()
        self.scene = mujoco.MjvScene(model, maxgeom=1000)
        self.context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
        self.option = mujoco.MjvOption()
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance, self.camera.elevation, self.camera.azimuth = self.DISTANCE, self.ELEVATION, self.AZIMUTH
        self.rect = mujoco.MjrRect(0, 0, width, height)
        self.payload_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "payload")
        self._rgb = np.empty((height, width, 3), np.uint8)

    def _add(self, geom_type, size, pos, rgba, ends=None, width: float = 0.0) -> None:
        mj, scene = self._mj, self.scene
        if scene.ngeom >= scene.maxgeom:
            return
        g = scene.geoms[scene.ngeom]
        mj.mjv_initGeom(g, geom_type, np.asarray(size, np.float64), np.asarray(pos, np.float64),
                        np.eye(3).reshape(-1), np.asarray(rgba, np.float32))
        if ends is not None:
            mj.mjv_connector(g, geom_type, width, np.asarray(ends[0], np.float64), np.asarray(ends[1], np.float64))
        scene.ngeom += 1

    def render(self, env, k: int, view: StepView) -> np.ndarray:
        mj = self._mj
        model, data = env.phys.models[k], env.phys.datas[k]
        self.gl.make_current()
        self.camera.lookat[:] = data.xpos[self.payload_body]
        mj.mjv_updateScene(model, data, self.option, None, self.camera, mj.mjtCatBit.mjCAT_ALL, self.scene)
        for j in range(self.scene.nlight):
            if self.scene.lights[j].headlight:
                self.scene.lights[j].ambient[:] = self.HEADLIGHT[0]
                self.scene.lights[j].diffuse[:] = self.HEADLIGHT[1]
        self._add(mj.mjtGeom.mjGEOM_CYLINDER, [0.15, 0.15, 0.005], [*view.goal_xy, 0.005],
                  [c / 255 for c in GOAL] + [0.8])
        # above the board: the proposal wide, the executed command thin just above it, so
        # both show where the QP left the proposal unchanged
        for a, colour, z, width in ((view.a_st, PROPOSED, CARRY_HEIGHT + 0.1, 0.06),
                                    (view.a_exec, EXECUTED, CARRY_HEIGHT + 0.18, 0.035)):
            tips = view.carrier_xy + ARROW_GAIN * view.world_step(a)
            for i in range(N_CARRIERS):
                if np.hypot(*(tips[i] - view.carrier_xy[i])) > 1e-3:
                    self._add(mj.mjtGeom.mjGEOM_ARROW, [0, 0, 0], [0, 0, 0], [c / 255 for c in colour] + [1.0],
                              ends=([*view.carrier_xy[i], z], [*tips[i], z]), width=width)
        mj.mjr_render(self.rect, self.scene, self.context)
        mj.mjr_readPixels(self._rgb, None, self.rect, self.context)
        return np.flipud(self._rgb).copy()   # OpenGL rows run bottom-up

    def close(self) -> None:
        if self.gl is not None:
            self.gl.make_current()
            self.context.free()
            self.gl.free()
            self.gl = None


# ------------------------------------------------------------------ overlay
class Overlay:
    """Header text on the scene and the per-carrier panel below it."""

    def __init__(self, width: int, panel_height: int, title: str):
        self.w, self.ph, self.title = width, panel_height, title
        self.font = _font(max(9, width // 40))
        self.small = _font(max(8, width // 48))

    def compose(self, scene: np.ndarray, view: StepView, outcome: str | None = None) -> np.ndarray:
        from PIL import Image, ImageDraw

        sh = scene.shape[0]
        img = Image.new("RGB", (self.w, sh + self.ph), (255, 255, 255))
        img.paste(Image.fromarray(scene), (0, 0))
        draw = ImageDraw.Draw(img, "RGBA")
        corr = float(np.linalg.norm(view.a_exec - view.a_st))
        lines = [self.title,
                 f"step {view.step}/{view.limit}   joint leaf {view.leaf_tuple}   "
                 f"||a_exec - a_ST|| {corr:.3f}   active rows {view.active_rows}"]
        if outcome:
            lines.append(outcome)
        fh = self.font.size if hasattr(self.font, "size") else 11
        draw.rectangle([0, 0, self.w, 6 + (fh + 3) * len(lines)], fill=(255, 255, 255, 190))
        for j, text in enumerate(lines):
            draw.text((6, 3 + j * (fh + 3)), text, font=self.font,
                      fill=ALERT if outcome and j == len(lines) - 1 else (0, 0, 0))
        self._panel(draw, sh, view)
        return np.asarray(img)

    def _panel(self, draw, top: int, view: StepView) -> None:
        cw = self.w // N_CARRIERS
        fh = self.small.size if hasattr(self.small, "size") else 10
        r = max(10, min(cw // 5, (self.ph - 2 * fh - 14) // 2))
        for i in range(N_CARRIERS):
            x0 = i * cw
            draw.line([(x0, top), (x0, top + self.ph)], fill=(200, 200, 200))
            who = "human (held)" if view.human_slot == i else f"leaf {int(view.leaf[i])}"
            draw.text((x0 + 5, top + 3), f"carrier {i}: {who}", font=self.small, fill=(0, 0, 0))
            # dx, dy in the carrier's own frame (x right, y up), the box [-1, 1]^2 as the circle
            c = np.array([x0 + 8 + r, top + fh + 10 + r], float)
            draw.ellipse([c[0] - r, c[1] - r, c[0] + r, c[1] + r], outline=(170, 170, 170))
            for a, colour, width in ((view.a_st[i], PROPOSED, 5), (view.a_exec[i], EXECUTED, 2)):
                _arrow(draw, c, c + r * np.array([a[0], -a[1]]), colour, width)
            # dyaw: two bars about a centre line
            bx, bw = c[0] + r + 12, cw - 2 * r - 30
            mid = bx + bw / 2
            for j, (a, colour) in enumerate(((view.a_st[i], PROPOSED), (view.a_exec[i], EXECUTED))):
                y = c[1] - 9 + 12 * j
                end = mid + 0.5 * bw * float(np.clip(a[2], -1, 1))
                draw.rectangle([min(mid, end), y, max(mid, end), y + 7], fill=colour)
            draw.line([(mid, c[1] - 12), (mid, c[1] + 14)], fill=(150, 150, 150))
            draw.text((bx, c[1] - 12 - fh - 2), "dyaw", font=self.small, fill=(90, 90, 90))
            corr = float(view.correction[i])
            draw.text((bx, c[1] + 16), f"corr. {corr:.3f}", font=self.small, fill=ALERT if corr > 1e-6 else (0, 0, 0))
            if corr > 1e-6:   # a bar growing with the correction, full width from 0.5 on
                y = c[1] + 18 + fh
                draw.rectangle([bx, y, bx + max(2.0, bw * min(corr / 0.5, 1.0)), y + 4], fill=ALERT)
        legend = "magenta: proposed a_ST (trees)   black: executed a_exec (exact QP)"
        draw.text((5, top + self.ph - fh - 4), legend, font=self.small, fill=(60, 60, 60))


# ------------------------------------------------------------------ writing
class _Writer:
    """Frames to ``path``: MP4 streamed to imageio-ffmpeg; GIF collected (palette images)
    and saved by Pillow at ``close``. ``append(frame, hold_s)`` repeats a frame (MP4) or lengthens
    its duration (GIF, where Pillow would merge identical frames anyway)."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = path, fps
        self.frames = 0
        self._mp4 = None
        self._gif: list = []
        self._palette = None
        self._durations: list[int] = []
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix.lower() == ".mp4":
            import imageio.v2 as imageio

            self._mp4 = imageio.get_writer(path, format="FFMPEG", fps=fps, codec="libx264", quality=6,
                                           pixelformat="yuv420p", macro_block_size=16, ffmpeg_log_level="error")

    def append(self, frame: np.ndarray, hold_s: float = 0.0) -> None:
        repeat = 1 + (round(hold_s * self.fps) if hold_s else 0)
        if self._mp4 is not None:
            for _ in range(repeat):
                self._mp4.append_data(frame)
            self.frames += repeat
            return
        from PIL import Image

        # one palette for all frames, undithered: stable colours, and Pillow can crop each frame
        # to what changed, which keeps GIFs small. The first frame's colours, plus the overlay's
        # own, which small areas (goal, arrows, bars) would otherwise lose to the median cut.
        img = Image.fromarray(frame)
        if self._palette is None:
            keys = [PROPOSED, EXECUTED, ALERT, GOAL, CARRIER, PAYLOAD, (255, 255, 255)]
            scene = img.quantize(colors=256 - len(keys), method=Image.Quantize.MEDIANCUT)
            self._palette = Image.new("P", (1, 1))
            self._palette.putpalette(scene.getpalette()[:3 * (256 - len(keys))] + [v for rgb in keys for v in rgb])
        self._gif.append(img.quantize(palette=self._palette, dither=Image.Dither.NONE))
        self._durations.append(round(1000.0 * repeat / self.fps))
        self.frames += 1

    def close(self) -> None:
        if self._mp4 is not None:
            self._mp4.close()
            self._mp4 = None
        elif self._gif:
            self._gif[0].save(self.path, save_all=True, append_images=self._gif[1:], duration=self._durations,
                              loop=0, optimize=False, disposal=1)
            self._gif = []


class VideoRecorder:
    """A deployment recorder that renders env ``cfg.episode``'s first episode to ``path``.

    Pass it as ``evaluate_policy(..., recorder=)``; call ``close()`` afterwards (it writes a
    GIF, finishes an MP4, and returns what was written). An episode that does not end within
    the loop leaves its frames so far, without an outcome frame."""

    def __init__(self, path: str | Path, cfg: VideoConfig = VideoConfig(), title: str = ""):
        self.path = Path(path)
        if self.path.suffix.lower() not in SUFFIXES:
            raise ValueError(f"video files are {' or '.join(SUFFIXES)}, got {self.path}")
        self.cfg, self.title = cfg, title
        self.width, self.scene_h, self.panel_h = frame_size(cfg.width)
        self._view = self._writer = self._overlay = None
        self._last: tuple[np.ndarray, StepView] | None = None
        self._steps = 0
        self.outcome: str | None = None

    def _start(self, env) -> None:
        if self.cfg.episode >= env.K:
            raise ValueError(f"video episode {self.cfg.episode} is not among the {env.K} evaluated episodes")
        if self.cfg.view == "camera":
            self._view = CameraView(env.phys.models[self.cfg.episode], self.width, self.scene_h)
        else:   # the episode's own layout
            k = self.cfg.episode
            self._view = TopDownView(env.spec, env.routes[k].points, self.width, self.scene_h, env.walls_array[k])
        fps = self.cfg.fps or 1.0 / (env.cfg.control_dt * self.cfg.every)
        self._writer = _Writer(self.path, fps)
        title = self.title or f"{env.cfg.scenario}, episode {self.cfg.episode}"
        self._overlay = Overlay(self.width, self.panel_h, title)

    def on_step(self, env, out, rows, decision, a_exec, active, live) -> None:
        if self._writer is None:
            self._start(env)
        k = self.cfg.episode
        if not live[k] or self.outcome is not None:
            return
        self._steps += 1
        if (self._steps - 1) % self.cfg.every:
            return
        view = StepView.of(env, k, decision, a_exec, active)
        scene = self._view.render(env, k, view)
        self._last = (scene, view)
        self._writer.append(self._overlay.compose(scene, view))

    def on_episode(self, k: int, metrics: dict) -> None:
        if k != self.cfg.episode or self._last is None:
            return
        steps = int(metrics["steps"])
        what = "success" if metrics["success"] else "payload dropped" if metrics["drop"] else "time limit"
        self.outcome = (f"outcome: {what} after {steps} steps, {int(metrics['collision_steps'])} contact steps, "
                        f"min clearance {float(metrics['min_clearance']):.2f} m")
        scene, view = self._last
        # the env has auto-reset by now: the outcome goes on the last state it showed
        self._writer.append(self._overlay.compose(scene, view, self.outcome), hold_s=self.cfg.hold_s)

    def close(self) -> dict:
        """Finish the file; {path, frames (as written), steps (of the episode seen), view, outcome}."""
        if isinstance(self._view, CameraView):
            self._view.close()
        written = {"path": None, "frames": 0, "steps": self._steps, "view": self.cfg.view, "outcome": self.outcome}
        if self._writer is not None:
            self._writer.close()
            written.update(path=str(self.path), frames=self._writer.frames)
        return written
