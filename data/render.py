"""Rendering with pyrender (offscreen, EGL) and the ``python -m data.render`` generation CLI.

This module is the only place in the project that knows OpenGL camera conventions:
``cv_to_gl_pose`` is the ONE conversion between our OpenCV ``cam2world`` and pyrender's camera pose.

One ``Renderer`` per process (``get_renderer``), reused for every scene (a mesh's GPU buffers belong to one GL
context) and kept until the process ends: pyrender's context teardown terminates the process's shared EGL display,
which would end every other renderer in it too, so there is no ``close``.
Each view is rendered twice: a multisampled colour pass for RGB, and a second pass into a framebuffer WITHOUT
multisampling, so z-depth is the exact depth at each pixel centre (pyrender's own depth comes from one MSAA
sub-sample, off the centre; see docs/data.md). The second pass is flat-shaded (scenes of generator versions 1-2:
pyrender's depth-only pass, which culls back faces).
"""

from __future__ import annotations

import numbers
import os
import sys

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

if not hasattr(np, "infty"):  # pyrender 0.1.45 still uses the alias numpy 2 removed
    np.infty = np.inf

import torch  # noqa: E402

from data.geom import MAX_SIDE  # noqa: E402
from data.scene import SCENE_VERSIONS  # noqa: E402
from pointmap.errors import ShapeError  # noqa: E402
from pointmap.geometry.cameras import K_LAYOUT, is_pinhole_K, is_rigid  # noqa: E402

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def cv_to_gl_pose(cam2world_cv: np.ndarray) -> np.ndarray:
    """OpenCV ``cam2world`` [4, 4] -> pyrender (OpenGL) camera pose [4, 4]. Its own inverse: applying
    it to a GL pose gives back the OpenCV pose (the flip is an involution)."""
    T = np.asarray(cam2world_cv, np.float64)
    if T.shape != (4, 4):
        raise ShapeError(f"cam2world expected [4, 4], got {list(T.shape)}")
    return T @ _CV_TO_GL


gl_to_cv_pose = cv_to_gl_pose  # same matrix: diag(1, -1, -1, 1) squared is the identity


class Renderer:
    """Offscreen pyrender renderer, one per process. ``render(scene, K, cam2world, w, h)`` returns
    (rgb uint8 [H, W, 3] or None, depth_z float32 [H, W] in metres, 0 = background)."""

    def __init__(self):
        import pyrender  # imported lazily: PYOPENGL_PLATFORM must be set first (done above)
        self._pyrender = pyrender

        class SeqNode(pyrender.Node):
            """A node hashed by its insertion number: pyrender keeps nodes in sets and draws meshes and
            sums lights in set order, which for default (address-based) hashes changes from process to
            process and gives last-bit pixel differences. Sequential hashes make the order fixed."""

            def __init__(self, seq, **kw):
                super().__init__(**kw)
                self._seq = seq

            def __hash__(self):
                return self._seq

            def __eq__(self, other):
                return self is other

        self._Node = SeqNode
        self._r = None
        self._size = None
        self._plain = None  # (fb, color rb, depth rb, (w, h)) without multisampling for the depth pass
        self._scene_key = None
        self._pscene = None
        self._cam_node = None
        self._legacy_depth = False

    # --- GL plumbing -----------------------------------------------------------------------------
    def _ensure(self, width, height):
        if self._r is None:
            self._r = self._pyrender.OffscreenRenderer(width, height)
        if (width, height) != self._size:
            self._r.viewport_width, self._r.viewport_height = width, height
            self._size = (width, height)

    def _plain_fb(self, width, height):
        from OpenGL import GL
        if self._plain is not None and self._plain[3] == (width, height):
            return self._plain[0]
        if self._plain is not None:
            GL.glDeleteFramebuffers(1, [self._plain[0]])
            GL.glDeleteRenderbuffers(2, [self._plain[1], self._plain[2]])
        cb, db = GL.glGenRenderbuffers(2)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, cb)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA, width, height)
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, db)
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT24, width, height)
        fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, fb)
        GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, cb)
        GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, db)
        self._plain = (fb, cb, db, (width, height))
        return fb

    # --- scenes ----------------------------------------------------------------------------------
    def set_scene(self, scene) -> None:
        """Build (once per scene) the pyrender scene for a ``data.scene.Scene``; again when the same object was
        changed since (surfaces added, removed or replaced, other lights, background, ambient light, extent or
        generator version). A mesh or material edited in place is not seen: give the surface a new one."""
        version = getattr(scene, "version", SCENE_VERSIONS[-1])
        if not (isinstance(version, (int, np.integer)) and not isinstance(version, bool) and version in SCENE_VERSIONS):
            raise ValueError(f"a scene's version expected a generator version (one of {SCENE_VERSIONS}), got {version!r}")
        built = (scene, _scene_state(scene, version))
        if self._scene_key is not None and self._scene_key[0] is scene and _same_state(self._scene_key[1], built[1]):
            return
        pr = self._pyrender
        ps = pr.Scene(bg_color=np.r_[scene.bg_color, 1.0], ambient_light=np.asarray(scene.ambient))
        # one primitive per material: draw calls dominate pyrender's cost, so merge surfaces sharing a look
        groups: dict[int, list] = {}
        for surf in scene.surfaces:
            groups.setdefault(id(surf.material), []).append(surf)
        textures = {}
        for surfs in groups.values():
            mat = surfs[0].material
            geo = [s.geometry() for s in surfs]
            pos = np.concatenate([g[0] for g in geo])
            nrm = np.concatenate([g[1] for g in geo])
            uv = np.concatenate([g[2] for g in geo])
            tex = None
            if mat.texture is not None:
                key = id(mat.texture)
                if key not in textures:
                    sampler = pr.Sampler(magFilter=0x2601, minFilter=0x2703)  # LINEAR, LINEAR_MIPMAP_LINEAR
                    textures[key] = pr.Texture(source=mat.texture, source_channels="RGB", sampler=sampler)
                tex = textures[key]
            material = pr.MetallicRoughnessMaterial(
                baseColorFactor=np.asarray(mat.base_color, np.float32), baseColorTexture=tex,
                metallicFactor=float(mat.metallic), roughnessFactor=float(mat.roughness), doubleSided=True)
            prim = pr.Primitive(positions=pos, normals=nrm, texcoord_0=uv if tex is not None else None,
                                material=material, mode=4)
            ps.add_node(self._Node(len(ps.nodes), mesh=pr.Mesh([prim])))
        for light in scene.lights:
            if light.kind == "directional":
                node = pr.DirectionalLight(color=light.color, intensity=light.intensity)
                pose = _light_pose(np.zeros(3), light.direction)
            elif light.kind == "point":
                node = pr.PointLight(color=light.color, intensity=light.intensity)
                pose = _light_pose(light.position, np.array([0.0, 0.0, -1.0]))
            elif light.kind == "spot":
                node = pr.SpotLight(color=light.color, intensity=light.intensity,
                                    innerConeAngle=light.inner_cone, outerConeAngle=light.outer_cone)
                pose = _light_pose(light.position, light.direction)
            else:
                raise ValueError(f"light kind expected directional/point/spot, got {light.kind!r}")
            kw = {"light": node} if isinstance(node, pr.light.Light) else {}
            ps.add_node(self._Node(len(ps.nodes), matrix=pose, **kw))
        # pyrender's depth-only pass culls back faces whatever the material says, though every material here is
        # double-sided as the colour pass draws it: an open or inside-out surface seen from behind showed in colour
        # with background depth (0) under it. Scenes of generator versions 1-2 keep that pass (their held-out sets
        # render again byte for byte); it also breaks ties between coplanar faces its own way (1-3 pixels a view)
        self._legacy_depth = version < 3
        self._pscene = ps
        self._scene_key = built
        self._cam_node = None
        self._extent = float(scene.extent)

    def _set_camera(self, K, cam2world, width, height, znear):
        pr = self._pyrender
        # pyrender puts pixel centres at half-integers: shift the OpenCV principal point by +0.5
        cam = pr.IntrinsicsCamera(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]) + 0.5,
                                  cy=float(K[1, 2]) + 0.5, znear=znear, zfar=_zfar(self._extent))
        if self._cam_node is not None:
            self._pscene.remove_node(self._cam_node)
        self._cam_node = self._Node(10**6, camera=cam, matrix=cv_to_gl_pose(cam2world))
        self._pscene.add_node(self._cam_node)
        self._pscene.main_camera_node = self._cam_node

    def render(self, scene, K, cam2world, width: int, height: int, *, color: bool = True, depth: bool = True,
               znear: float = 0.05):
        """Render one view of a ``data.scene.Scene`` with OpenCV ``K`` and ``cam2world``.

        Returns (rgb uint8 [H, W, 3] or None, depth_z float32 [H, W] or None)."""
        K = np.asarray(K, np.float64)
        cam2world = np.asarray(cam2world, np.float64)
        if K.shape != (3, 3) or cam2world.shape != (4, 4):
            raise ShapeError(f"K expected [3, 3] and cam2world [4, 4], got {list(K.shape)} and {list(cam2world.shape)}")
        # what the ground truth would silently get wrong: a transposed or mirrored K, a NaN one (all background), a
        # scaled cam2world (depths scaled by it)
        if not bool(is_pinhole_K(K)):
            raise ShapeError(f"K expected pinhole intrinsics {K_LAYOUT} with positive focals, got {K.tolist()}")
        if not bool(is_rigid(torch.from_numpy(cam2world))):
            raise ShapeError(f"cam2world expected a finite rigid transform (a rotation and a translation), got "
                             f"{cam2world.tolist()}")
        if not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) and 1 <= n <= MAX_SIDE
                   for n in (width, height)):
            raise ShapeError(f"image size expected ints in [1, {MAX_SIDE}], got {width!r}x{height!r}")
        if not (isinstance(znear, numbers.Real) and not isinstance(znear, bool) and 0 < znear < _zfar(scene.extent)):
            raise ShapeError(f"znear expected a distance in metres above 0 and below the far plane (4 x the scene's "
                             f"extent, at least 50 m: {_zfar(scene.extent):g}), got {znear!r}")
        pr = self._pyrender
        self.set_scene(scene)
        self._ensure(int(width), int(height))
        self._set_camera(K, cam2world, width, height, znear)
        rgb = None
        if color:
            rgb, _ = self._r.render(self._pscene, flags=pr.RenderFlags.NONE)
            rgb = np.ascontiguousarray(rgb)
        d = self._depth_pass(int(width), int(height)) if depth else None
        return rgb, d

    def _depth_pass(self, width, height):
        pr = self._pyrender
        inner = self._r._renderer
        self._r._platform.make_current()
        inner.viewport_width, inner.viewport_height = width, height
        inner._configure_main_framebuffer()
        plain = self._plain_fb(width, height)
        saved = inner._main_fb_ms
        inner._main_fb_ms = plain  # draw into the single-sample buffer; pyrender then blits and reads it
        try:
            if self._legacy_depth:  # what generator versions 1-2 rendered: their datasets render again identically
                depth = self._r.render(self._pscene, flags=pr.RenderFlags.DEPTH_ONLY)
            else:  # a flat-shaded pass: depth of every face the colour pass draws, back faces too
                _, depth = self._r.render(self._pscene, flags=pr.RenderFlags.FLAT)
        finally:
            inner._main_fb_ms = saved
        return np.ascontiguousarray(depth, dtype=np.float32)


def _zfar(extent) -> float:
    """The far plane for a scene of ``extent`` metres: 4 x its extent, at least 50 m."""
    return max(4 * float(extent), 50.0)


def _scene_state(scene, version: int) -> tuple:
    """What ``Renderer.set_scene`` builds from: the surfaces' meshes and materials (the objects themselves, compared
    by identity) and the lights, ambient light, background, extent and generator version (by value)."""
    return (tuple((s.mesh, s.material, s.smooth) for s in scene.surfaces), repr(scene.lights),
            np.asarray(scene.ambient).tolist(), np.asarray(scene.bg_color).tolist(), float(scene.extent), version)


def _same_state(a: tuple, b: tuple) -> bool:
    return (len(a[0]) == len(b[0]) and all(x[0] is y[0] and x[1] is y[1] and x[2] == y[2] for x, y in zip(a[0], b[0]))
            and a[1:] == b[1:])


def _light_pose(position, direction):
    """Pose of a pyrender light (it shines along its local -z) at ``position`` pointing ``direction``."""
    d = np.asarray(direction, np.float64)
    if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) < 1e-12:
        raise ValueError(f"a light's direction expected a finite non-zero 3-vector, got {direction!r}")
    d = d / np.linalg.norm(d)
    z = -d
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, position
    return T


_RENDERER: Renderer | None = None


def get_renderer() -> Renderer:
    """The process's shared renderer (created on first use)."""
    global _RENDERER
    if _RENDERER is None:
        _RENDERER = Renderer()
    return _RENDERER


def main(argv=None) -> int:
    from data.generate import main as generate_main
    return generate_main(argv)


if __name__ == "__main__":
    sys.exit(main())
