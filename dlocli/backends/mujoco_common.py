"""What both MuJoCo backends share: importing MuJoCo (headless GL chosen first), its warnings
counted rather than printed, the rest shape of a sagging rod, MJCF number formatting and
rendering (an offscreen MuJoCo image, or the matplotlib fallback without GL)."""

from __future__ import annotations

import contextlib
import ctypes.util
import os
import sys
import warnings
import weakref

import numpy as np

from dlocli.backends.render import finite_points, render_rod
from dlocli.errors import BadInput


def _choose_headless_gl() -> str | None:
    """Without a display, ask MuJoCo for EGL (or OSMesa) if its libraries are present.

    MuJoCo reads MUJOCO_GL once, when it is imported. Returns the choice made, if any.
    """
    if "MUJOCO_GL" in os.environ or os.environ.get("DISPLAY"):
        return None
    find = ctypes.util.find_library
    if find("EGL") and (find("OpenGL") or find("GL")):
        os.environ["MUJOCO_GL"] = "egl"
    elif find("OSMesa"):
        os.environ["MUJOCO_GL"] = "osmesa"
    return os.environ.get("MUJOCO_GL")


def _forget_gl_imports(had_pyopengl_platform: bool) -> None:
    """Undo a failed ``import mujoco`` with our GL choice, so it can be imported without GL."""
    for name in [n for n in sys.modules if n.split(".")[0] in ("mujoco", "OpenGL")]:
        del sys.modules[name]
    if not had_pyopengl_platform:
        os.environ.pop("PYOPENGL_PLATFORM", None)  # MuJoCo's GL modules set it
    os.environ["MUJOCO_GL"] = "disable"


def _refuse_a_split_install_over_mujoco3(error: Exception) -> None:
    """MuJoCo 4 comes as `mujoco` plus `mujoco-core`; pip upgrading an environment that had
    MuJoCo 3 in place writes mujoco-core's files, then removes the old package's files at the
    same paths, and `import mujoco` then fails naming mujoco-core: say so in one line."""
    if isinstance(error, ImportError) and "mujoco-core" in str(error):
        from importlib.metadata import version

        pins = " ".join(f"{name}=={version('mujoco')}" for name in _SPLIT_PACKAGES)
        raise BadInput(
            "MuJoCo's core bindings (mujoco-core) are missing or broken, as pip leaves them "
            "when MuJoCo 4 is installed over MuJoCo 3 in the same environment; repair with: "
            f"pip install --force-reinstall --no-deps {pins}"
        ) from None


#: the packages MuJoCo 4 comes in, reinstalled together to repair a broken install
_SPLIT_PACKAGES = ("mujoco", "mujoco-core", "mujoco-studio")


_had_pyopengl_platform = "PYOPENGL_PLATFORM" in os.environ
_gl_choice = _choose_headless_gl()
try:
    import mujoco
except Exception as error:  # a broken GL stack must not take the physics down: render() falls back
    _refuse_a_split_install_over_mujoco3(error)
    if _gl_choice is None:
        raise
    _forget_gl_imports(_had_pyopengl_platform)
    import mujoco


def _keep_warnings_counted_only(message: str) -> None:
    """MuJoCo's warnings (an unstable simulation, ...) are counted in ``MjData.warning``,
    which the backend checks; printed, they would come before the one-line error, and MuJoCo
    would append them to a MUJOCO_LOG.TXT in the working directory."""
    del message


mujoco.set_mju_user_warning(_keep_warnings_counted_only)
_GL_BROKEN = False  # set once per process when no GL context can be made: no retry noise
#: MJCF of the offscreen buffer (the largest image render() makes) and the sky, and the light
SCENE_XML = """<visual><global offwidth="1920" offheight="1440"/></visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.95 0.95 0.97"
             rgb2="0.75 0.8 0.88" width="64" height="64"/>
  </asset>"""
LIGHT_XML = '<light pos="0 -1 3" dir="0 0.3 -1" directional="true"/>'

#: the installed MuJoCo's major version: 3 runs the composite cable, 4 removed it
MUJOCO_MAJOR = int(mujoco.__version__.split(".")[0])


def rest_polyline(n_segments: int, length: float, chord: float) -> np.ndarray:
    """(N+1,3) vertices (m) of a rod of equal segments from the origin to (chord, 0, 0).

    The first and last segments lie along +x (so both grippers have identity orientation)
    and the rod sags in the xz-plane with the profile of the first clamped buckling mode:
    segment angles ``-A sin(2 pi i / (N-1))``, A found by bisection to match the chord. A
    chord of at least the length gives a straight rod.
    """
    seg = length / n_segments
    if chord >= length * (1.0 - 1e-9):
        angles = np.zeros(n_segments)
    else:
        profile = np.sin(2.0 * np.pi * np.arange(n_segments) / (n_segments - 1))
        low, high = 0.0, 0.5 * np.pi
        for _ in range(60):  # chord(A) decreases monotonically on [0, pi/2]
            mid = 0.5 * (low + high)
            low, high = (mid, high) if seg * np.cos(mid * profile).sum() > chord else (low, mid)
        angles = -0.5 * (low + high) * profile
    steps = seg * np.stack([np.cos(angles), np.zeros(n_segments), np.sin(angles)], axis=1)
    return np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])


def fmt_numbers(values: np.ndarray | tuple[float, ...] | list[float]) -> str:
    """Numbers as MJCF attribute text, 12 significant digits."""
    return " ".join(f"{float(v):.12g}" for v in np.ravel(values))


class MujocoRendering:
    """Rendering for a MuJoCo backend: needs ``model``, ``data``, ``rod``, ``_renderer`` and
    ``_renderer_finalizer`` (both None at first) and the backend's observation methods."""

    def render(
        self, width: int = 480, height: int = 360, goal: np.ndarray | None = None
    ) -> np.ndarray:
        """Offscreen MuJoCo image if a GL context can be made, else the matplotlib fallback.

        A goal that is not a finite (M,3) array is not drawn.
        """
        goal_points = finite_points(goal)
        try:
            image = self._render_gl(width, height, goal_points)
        except Exception as exc:  # any GL failure means "no GL here": fall back, never crash
            _mark_gl_broken(exc)
            image = None
        if image is not None:
            return image
        try:
            return render_rod(
                self.segment_positions(),
                self.gripper_poses(),
                goal_points,
                width,
                height,
                rod_length=self.rod.length,
            )
        except Exception as exc:  # a blank frame beats a crashed episode or video
            warnings.warn(
                f"rod rendering failed ({exc!r}); returning a blank image",
                RuntimeWarning,
                stacklevel=2,
            )
            return np.full((max(1, int(height)), max(1, int(width)), 3), 255, dtype=np.uint8)

    def _render_gl(self, width: int, height: int, goal: np.ndarray | None) -> np.ndarray | None:
        if _GL_BROKEN or not hasattr(mujoco, "Renderer"):
            return None
        offscreen = self.model.vis.global_
        if width > offscreen.offwidth or height > offscreen.offheight:
            return None
        renderer = self._renderer
        if renderer is None or (renderer.width, renderer.height) != (width, height):
            self._close_renderer()
            renderer = self._renderer = mujoco.Renderer(self.model, height, width)
            # close it before interpreter exit: MuJoCo's EGL atexit hook (registered earlier,
            # so run later) would otherwise leave GLContext.__del__ failing noisily
            self._renderer_finalizer = weakref.finalize(self, _close_quietly, renderer)
        renderer.update_scene(self.data, camera=self._camera())
        if goal is not None:
            self._add_goal(renderer.scene, goal)
        return renderer.render().copy()

    def _camera(self) -> mujoco.MjvCamera:
        """A fixed free camera in front of the workspace (looking along +y, x to the right)."""
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.lookat[:] = (0.0, 0.0, 0.7 * self.rod.length)
        camera.distance = 1.8 * self.rod.length  # the 45 degree view spans the workspace
        camera.azimuth = 90.0
        camera.elevation = -10.0
        return camera

    def _add_goal(self, scene: mujoco.MjvScene, goal: np.ndarray) -> None:
        """Goal segment centres (M,3) as small green spheres (scene user geoms)."""
        size = np.array([1.5 * self.rod.radius, 0.0, 0.0])
        rgba = np.array([0.1, 0.8, 0.2, 0.7], dtype=np.float32)
        eye = np.eye(3).ravel()
        for point in goal[: max(0, scene.maxgeom - scene.ngeom)]:
            mujoco.mjv_initGeom(
                scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, size, point, eye, rgba
            )
            scene.ngeom += 1

    def _close_renderer(self) -> None:
        if self._renderer_finalizer is not None:
            self._renderer_finalizer.detach()
            self._renderer_finalizer = None
        if self._renderer is not None:
            renderer, self._renderer = self._renderer, None
            _close_quietly(renderer)

    def close(self) -> None:
        self._close_renderer()


def _close_quietly(renderer: mujoco.Renderer) -> None:
    # a half-made or already torn-down GL context has nothing left to release
    with contextlib.suppress(Exception):
        renderer.close()


def _mark_gl_broken(exc: Exception) -> None:
    global _GL_BROKEN
    if not _GL_BROKEN:
        warnings.warn(
            f"MuJoCo offscreen rendering unavailable ({type(exc).__name__}); "
            "using the matplotlib renderer",
            RuntimeWarning,
            stacklevel=3,
        )
    _GL_BROKEN = True
