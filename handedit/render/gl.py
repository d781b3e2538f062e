"""A pyrender OffscreenRenderer tuned for software GL (Mesa llvmpipe) and many contexts.

pyrender 0.1.45 is used as is, with seven instance-level adjustments that cut a 640x480 frame
from ~200 ms to well under 100 ms on llvmpipe without changing the silhouette:
- single-sample framebuffer (pyrender hard-codes 4x MSAA; our alpha is binary anyway),
- a cheaper Blinn-Phong shader with pyrender's uniforms (``shaders.py``), each uniform sent
  only when its value changes,
- opaque meshes drawn front to back (pyrender sorts back to front, defeating early-z),
- the (fixed) lights bound once per program per frame, not before every primitive,
- clear and read back only ``gl.region`` when it is set (the robot's screen box), from the
  drawn buffers themselves when they are single-sample (no resolve blit): the full-frame
  read-back and its depth conversion were a third of a frame's cost,
- EGL teardown that does not eglTerminate the process-wide display (which kills other contexts).

``Scene`` is pyrender's scene with its node sets in insertion order: pyrender keeps nodes in
Python sets, which iterate in memory-address order, so the draw order of equally distant meshes
(a nail on its finger segment, links sharing an origin) and the order lights are summed in the
shader changed from one process to the next: the same inputs rendered different pixels.
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Iterable, MutableSet

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
from pyrender.shader_program import ShaderProgramCache  # noqa: E402

from handedit.render.shaders import shader_dir  # noqa: E402


class _InsertionOrdered(MutableSet):
    """A set that iterates in insertion order (what pyrender's node sets need to be)."""

    def __init__(self, items: Iterable = ()):
        self._items = dict.fromkeys(items)

    def __contains__(self, item) -> bool:
        return item in self._items

    def __iter__(self):
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def add(self, item) -> None:
        self._items[item] = None

    def discard(self, item) -> None:
        self._items.pop(item, None)


_NODE_SETS = ("_nodes", "_mesh_nodes", "_point_light_nodes", "_spot_light_nodes", "_directional_light_nodes",
              "_camera_nodes")


class Scene(pyrender.Scene):
    """pyrender's scene, iterated in the order nodes were added: same scene, same pixels."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._order_node_sets()

    def clear(self) -> None:
        super().clear()
        self._order_node_sets()

    def _order_node_sets(self) -> None:
        for name in _NODE_SETS:
            setattr(self, name, _InsertionOrdered(getattr(self, name)))


class _RobotShaderCache(ShaderProgramCache):
    """Swaps pyrender's PBR mesh shader for ours; every other program is pyrender's."""

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        if vertex_shader == "mesh.vert" and fragment_shader == "mesh.frag" and defines and "NORMAL_LOC" in defines:
            d = shader_dir()
            vertex_shader, fragment_shader = str(d / "robot.vert"), str(d / "robot.frag")
        program = super().get_program(vertex_shader, fragment_shader, geometry_shader, defines)
        if not getattr(program, "_skips_repeats", False):
            _skip_repeated_uniforms(program)
        return program


def _skip_repeated_uniforms(program) -> None:
    """pyrender sends the camera's V, P and position before every primitive (a uniform costs
    ~60 us in PyOpenGL): a value equal to the one the program already holds is not re-sent
    (GL keeps uniform values in the program object, and only this wrapper writes them)."""
    set_uniform, last = program.set_uniform, {}

    def set_if_changed(name, value, unsigned=False):
        v = np.array(value) if isinstance(value, (np.ndarray, list, tuple)) else value
        prev = last.get(name)
        if prev is not None and type(prev) is type(v) and (np.array_equal(prev, v) if isinstance(v, np.ndarray) else prev == v):
            return
        set_uniform(name, value, unsigned)
        last[name] = v

    program.set_uniform, program._skips_repeats = set_if_changed, True


def _front_to_back(renderer):
    def sorted_mesh_nodes(scene):
        cam = scene.get_pose(scene.main_camera_node)[:3, 3]
        nodes = [n for n in scene.mesh_nodes if not n.mesh.is_transparent]
        nodes.sort(key=lambda n: np.linalg.norm(scene.get_pose(n)[:3, 3] - cam))
        return nodes + [n for n in scene.mesh_nodes if n.mesh.is_transparent]

    renderer._sorted_mesh_nodes = sorted_mesh_nodes


def _single_sample(gl: pyrender.OffscreenRenderer) -> None:
    from OpenGL.GL import GL_DEPTH_COMPONENT24, GL_RENDERBUFFER, GL_RGBA, glBindRenderbuffer, glRenderbufferStorageMultisample

    r = gl._renderer
    r._configure_main_framebuffer()  # allocates pyrender's buffers now so we can resize them
    for rb, fmt in ((r._main_cb_ms, GL_RGBA), (r._main_db_ms, GL_DEPTH_COMPONENT24)):
        glBindRenderbuffer(GL_RENDERBUFFER, rb)
        glRenderbufferStorageMultisample(GL_RENDERBUFFER, 0, fmt, r.viewport_width, r.viewport_height)
    glBindRenderbuffer(GL_RENDERBUFFER, 0)


def _bind_lighting_once_per_frame(gl: pyrender.OffscreenRenderer) -> None:
    """pyrender re-sends every light uniform before each primitive (Python; measured 59 -> 50
    CPU ms per 640x480 Allegro frame on llvmpipe when skipped). Our lights are fixed, unshadowed and
    fewer than pyrender's per-program maximum, so the values only need setting once per program
    per frame (GL keeps uniform values in the program object): identical output."""
    renderer = gl._renderer
    bind, forward = renderer._bind_lighting, renderer._forward_pass
    bound: set[int] = set()

    def bind_lighting(scene, program, node, flags):
        if id(program) not in bound:
            bind(scene, program, node, flags)
            bound.add(id(program))

    def forward_pass(scene, flags, seg_node_map=None):
        bound.clear()
        return forward(scene, flags, seg_node_map=seg_node_map)

    renderer._bind_lighting, renderer._forward_pass = bind_lighting, forward_pass


def _region_reads(gl: pyrender.OffscreenRenderer) -> None:
    """``gl.region = (x, y, w, h)`` (OpenCV pixels: top-left origin): the next renders clear and
    return only that box (a scissor on the clear and the draws; the resolve blit and
    ``glReadPixels`` of the box), the same pixels as the full frame's crop. None: full frame."""
    from OpenGL.GL import (GL_COLOR_BUFFER_BIT, GL_DEPTH_BUFFER_BIT, GL_DEPTH_COMPONENT, GL_DRAW_FRAMEBUFFER, GL_FLOAT,
                           GL_LINEAR, GL_NEAREST, GL_READ_FRAMEBUFFER, GL_RGBA, GL_SCISSOR_TEST, GL_UNSIGNED_BYTE,
                           glBindFramebuffer, glBlitFramebuffer, glDisable, glEnable, glReadPixels, glScissor)

    r = gl._renderer
    gl.region = None
    full_read, forward = r._read_main_framebuffer, r._forward_pass

    def gl_box():
        x, y, w, h = gl.region
        return x, r._main_fb_dims[1] - (y + h), w, h  # GL rows count from the bottom

    def forward_pass(scene, flags, seg_node_map=None):
        if gl.region is None:
            return forward(scene, flags, seg_node_map=seg_node_map)
        glEnable(GL_SCISSOR_TEST)
        glScissor(*gl_box())
        try:
            return forward(scene, flags, seg_node_map=seg_node_map)
        finally:
            glDisable(GL_SCISSOR_TEST)

    def read(scene, flags):
        if gl.region is None or not flags & pyrender.RenderFlags.RGBA:
            return full_read(scene, flags)
        x, y, w, h = gl_box()
        glBindFramebuffer(GL_READ_FRAMEBUFFER, r._main_fb_ms)
        if not getattr(gl, "single_sample", False):  # resolve the samples; single-sample buffers are read as drawn
            glBindFramebuffer(GL_DRAW_FRAMEBUFFER, r._main_fb)
            glBlitFramebuffer(x, y, x + w, y + h, x, y, x + w, y + h, GL_COLOR_BUFFER_BIT, GL_LINEAR)
            glBlitFramebuffer(x, y, x + w, y + h, x, y, x + w, y + h, GL_DEPTH_BUFFER_BIT, GL_NEAREST)
            glBindFramebuffer(GL_READ_FRAMEBUFFER, r._main_fb)
        window = np.frombuffer(glReadPixels(x, y, w, h, GL_DEPTH_COMPONENT, GL_FLOAT), np.float32).reshape(h, w)[::-1]
        # pyrender's conversion of window depth to camera z (float32 as pyrender's), on the box only
        near, far = scene.main_camera_node.camera.znear, scene.main_camera_node.camera.zfar
        depth = (2.0 * near * far) / (far + near - (2.0 * window - 1.0) * (far - near))
        np.copyto(depth, 0.0, where=window == 1.0)
        color = np.frombuffer(glReadPixels(x, y, w, h, GL_RGBA, GL_UNSIGNED_BYTE), np.uint8).reshape(h, w, 4)[::-1].copy()
        return color, depth

    r._forward_pass, r._read_main_framebuffer = forward_pass, read


def _keep_display_alive(gl: pyrender.OffscreenRenderer) -> None:
    """pyrender's EGL teardown calls eglTerminate on the process-wide display, which invalidates
    every other renderer's context (EGL_BAD_DISPLAY). Destroy only our own context instead, and
    give back the context that was current: a renderer dropped without ``close`` is deleted by
    the garbage collector, which may run in the middle of another renderer's frame."""
    platform = gl._platform
    if not hasattr(platform, "_egl_display"):
        return
    delete = gl.delete

    def delete_keeping_current() -> None:
        from OpenGL.EGL import EGL_DRAW, EGL_READ, eglGetCurrentContext, eglGetCurrentDisplay, eglGetCurrentSurface, eglMakeCurrent

        def address(p) -> int | None:
            return None if p is None else ctypes.cast(p, ctypes.c_void_p).value

        ctx = eglGetCurrentContext()
        current = (eglGetCurrentDisplay(), eglGetCurrentSurface(EGL_DRAW), eglGetCurrentSurface(EGL_READ), ctx)
        other = address(ctx) not in (None, address(platform._egl_context))
        delete()
        if other:
            eglMakeCurrent(*current)

    gl.delete = delete_keeping_current

    def delete_context() -> None:
        from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

        if platform._egl_context is not None:
            eglMakeCurrent(platform._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
            eglDestroyContext(platform._egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None

    platform.delete_context = delete_context


def make_offscreen(width: int, height: int, msaa: bool = False) -> pyrender.OffscreenRenderer:
    """OffscreenRenderer bound to the calling thread, with the adjustments above."""
    gl = pyrender.OffscreenRenderer(width, height)
    _keep_display_alive(gl)
    gl._platform.make_current()
    gl._renderer._program_cache = _RobotShaderCache()
    _front_to_back(gl._renderer)
    _region_reads(gl)
    _bind_lighting_once_per_frame(gl)
    if not msaa:
        _single_sample(gl)
        gl.single_sample = True
    return gl
