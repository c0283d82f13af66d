"""CPU rasterizer: moderngl on a standalone EGL context (Mesa llvmpipe), OpenCV camera conventions.

Per image:

1. The distorted camera's pixel centres are undistorted once per camera (cached) and a pinhole camera
   with the same focal lengths and a shifted principal point is chosen that covers all of them
   (plus a 2-pixel margin).
2. Id pass (no multisampling): triangle id + 1 into an R32I buffer of the pinhole image.
3. Colour pass (4x MSAA unless ``msaa=False``): Lambert-shaded albedo texture (mipmapped, anisotropic)
   with painted dots, into a float buffer of the pinhole image. With ``lights``: first one depth pass per
   shadowing light into an R32F shadow map, then linear-light GGX + Lambert shading
   (:mod:`rigbuild.render.lights`).
4. Colour is resampled to the distorted image with ``cv2.remap`` (bilinear). Depth, triangle id and
   barycentrics at the distorted pixel centres are never interpolated: a full-screen GLSL pass intersects
   each pixel's exact ray (double precision) with the triangles found at the 2x2 pinhole pixel centres
   around it (a projected triangle is convex, so four equal ids settle it); the few pixels whose
   candidates all miss (sub-pixel slivers at silhouettes) get a numpy search of the neighbouring
   triangles (:func:`rigbuild.render.common.ring_search`). Then Gaussian sensor noise and 8-bit rounding.
   (:func:`rigbuild.render.common.resolve_from_id_buffer` is the same algorithm in numpy.)

The GL projection maps OpenCV pixel centre ``(u, v)`` (integers) to GL window coordinates
``(u + 0.5, v + 0.5)``, and rows are read back bottom-up, so buffer row ``v`` is image row ``v``.
"""

from __future__ import annotations

import weakref

import numpy as np

from rigbuild.camera import Camera
from rigbuild.render.common import (DOT_CANDIDATES, RenderOptions, RenderResult, background_rgb, dot_candidates,
                                    empty_result, finish_color, finish_outputs, light_in_camera, lights_in_camera,
                                    pixel_rays, ring_search,
                                    shadow_frame, srgb_to_linear, vogel_taps)
from rigbuild.render.mesh import TexturedMesh

PINHOLE_MARGIN_PX = 2
MSAA_SAMPLES = 4
ANISOTROPY = 8.0
#: The lit shader tries only each triangle's candidate dots (rigbuild.render.common.dot_candidates, within
#: radius + this of the triangle) where the pixel footprint is below it, mm; elsewhere every dot.
DOT_MARGIN_MM = 2.0

_ID_VS = """
#version 330
uniform mat4 proj;
in vec3 in_pos;
void main() { gl_Position = proj * vec4(in_pos, 1.0); }
"""
_ID_FS = """
#version 330
out int out_id;
void main() { out_id = gl_PrimitiveID + 1; }
"""
_COLOR_VS = """
#version 330
uniform mat4 proj;
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
out vec3 v_pos;
out vec3 v_normal;
out vec2 v_uv;
void main() {
    v_pos = in_pos; v_normal = in_normal; v_uv = in_uv;
    gl_Position = proj * vec4(in_pos, 1.0);
}
"""
_COLOR_FS = """
#version 330
uniform sampler2D albedo;
uniform sampler2D dots;      // RGBA32F, one texel per dot: camera-frame centre (mm), radius (mm)
uniform int n_dots;
uniform vec3 dot_albedo;     // 0..1
uniform vec3 light_dir;      // camera frame, unit, towards the light
uniform float ambient;
in vec3 v_pos;
in vec3 v_normal;
in vec2 v_uv;
out vec4 out_color;
void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, v_pos) > 0.0) n = -n;            // two-sided: face the camera at the origin
    vec3 a = texture(albedo, v_uv).rgb;
    if (n_dots > 0) {
        float fw = max(length(fwidth(v_pos)), 1e-6);   // pixel footprint on the surface, mm
        float cover = 0.0;
        for (int i = 0; i < n_dots; i++) {
            vec4 d = texelFetch(dots, ivec2(i, 0), 0);
            cover = max(cover, clamp((d.w - length(v_pos - d.xyz)) / fw + 0.5, 0.0, 1.0));
        }
        a = mix(a, dot_albedo, cover);
    }
    float shade = ambient + (1.0 - ambient) * max(dot(n, light_dir), 0.0);
    out_color = vec4(a * shade * 255.0, 1.0);  // float buffer, 8-bit levels: rounded once, at the end
}
"""
# Per-dot paint colours on the legacy (8-bit Lambert) path: row 1 of the dots texture holds RGB (0..1).
_COLOR_FS_DOT_COLORS = _COLOR_FS.replace(
    "        float cover = 0.0;\n",
    "        float cover = 0.0;\n        int which = 0;\n").replace(
    "            cover = max(cover, clamp((d.w - length(v_pos - d.xyz)) / fw + 0.5, 0.0, 1.0));\n",
    "            float ci = clamp((d.w - length(v_pos - d.xyz)) / fw + 0.5, 0.0, 1.0);\n"
    "            if (ci > cover) { cover = ci; which = i; }\n").replace(
    "        a = mix(a, dot_albedo, cover);",
    "        a = mix(a, texelFetch(dots, ivec2(which, 1), 0).rgb, cover);")

_LIT_VS = """
#version 400
uniform mat4 proj;
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
in vec2 in_mat;
in ivec4 in_dots;
out vec3 v_pos;
out vec3 v_normal;
out vec2 v_uv;
out vec2 v_mat;
flat out ivec4 v_dots;
void main() {
    v_pos = in_pos; v_normal = in_normal; v_uv = in_uv; v_mat = in_mat; v_dots = in_dots;
    gl_Position = proj * vec4(in_pos, 1.0);
}
"""
# Linear-light GGX + Lambert shading with shadow maps (the model of rigbuild.render.lights; numpy twin:
# rigbuild.render.common.ggx_shade and shadow_visibility).
_LIT_FS = """
#version 400
#define PI 3.14159265358979
uniform sampler2D albedo;
uniform sampler2D matmap;     // RGB32F: F0, roughness
uniform int use_map_f0;
uniform int use_map_rough;
uniform sampler2D dots;       // width M, row 0: camera-frame centre (mm), radius (mm); row 1: RGB 0..1
uniform int n_dots;
uniform vec2 dot_mat;         // paint F0, roughness (< 0: keep the skin's)
uniform float dot_margin;     // mm: v_dots lists every dot within radius + dot_margin of the triangle
uniform int n_lights;
uniform int l_kind[8];        // 0 ambient, 1 directional, 2 point
uniform vec3 l_vec[8];        // towards the light (unit) or position (mm), camera frame
uniform vec3 l_rad[8];
uniform float l_ref2[8];
uniform int l_smap[8];        // shadow map index, -1 none
uniform float l_soft[8];
uniform sampler2D smap[4];    // R32F light-frame depth
uniform mat4 s_view[4];       // camera frame -> light frame
uniform vec4 s_proj[4];       // a, cu, cv, perspective
uniform int s_size;
uniform vec2 taps[16];
in vec3 v_pos;
in vec3 v_normal;
in vec2 v_uv;
in vec2 v_mat;
flat in ivec4 v_dots;         // the triangle's candidate dots, ascending, -1 after the last; x = -2: too many
out vec4 out_color;

vec3 srgb2lin(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), greaterThan(c, vec3(0.04045)));
}

float cmp(int s, ivec2 ij, float ref) {
    if (any(lessThan(ij, ivec2(0))) || any(greaterThanEqual(ij, ivec2(s_size)))) return 1.0;
    return ref <= texelFetch(smap[s], ij, 0).x ? 1.0 : 0.0;
}

float visibility(int s, vec3 p, float nl, float soft) {
    vec4 q = s_view[s] * vec4(p, 1.0);
    vec4 pr = s_proj[s];
    bool persp = pr.w > 0.5;
    float w = persp ? q.z : 1.0;
    vec2 uv = pr.x * q.xy / w + pr.yz;
    float tmm = persp ? q.z / pr.x : 1.0 / pr.x;
    float c = clamp(nl, 1e-4, 1.0);
    float tn = min(sqrt(1.0 - c * c) / c, 10.0);
    float r = soft / tmm;
    float ref = q.z - tmm * (1.0 + (1.5 + r) * tn);
    int nt = soft > 0.0 ? 16 : 1;
    float acc = 0.0;
    for (int k = 0; k < nt; k++) {
        vec2 t = soft > 0.0 ? uv + taps[k] * r : uv;
        vec2 f = floor(t);
        vec2 fr = t - f;
        ivec2 i0 = ivec2(f);
        float c00, c10, c01, c11;
        if (all(greaterThanEqual(i0, ivec2(0))) && all(lessThan(i0, ivec2(s_size - 1)))) {
            // the 2x2 texels in one fetch: the footprint of (i0 + 1) / size is i0..i0+1 exactly
            // (x: (i0.x, i0.y + 1), y: (i0.x + 1, i0.y + 1), z: (i0.x + 1, i0.y), w: i0)
            vec4 g = textureGather(smap[s], (vec2(i0) + 1.0) / float(s_size));
            c00 = ref <= g.w ? 1.0 : 0.0;
            c10 = ref <= g.z ? 1.0 : 0.0;
            c01 = ref <= g.x ? 1.0 : 0.0;
            c11 = ref <= g.y ? 1.0 : 0.0;
        } else {
            c00 = cmp(s, i0, ref);
            c10 = cmp(s, i0 + ivec2(1, 0), ref);
            c01 = cmp(s, i0 + ivec2(0, 1), ref);
            c11 = cmp(s, i0 + ivec2(1, 1), ref);
        }
        acc += (1.0 - fr.x) * (1.0 - fr.y) * c00 + fr.x * (1.0 - fr.y) * c10
             + (1.0 - fr.x) * fr.y * c01 + fr.x * fr.y * c11;
    }
    return acc / float(nt);
}

void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, v_pos) > 0.0) n = -n;
    vec3 a = texture(albedo, v_uv).rgb;
    vec2 fr = v_mat;
    if (use_map_f0 + use_map_rough > 0) {
        vec2 m = texture(matmap, v_uv).rg;
        if (use_map_f0 > 0) fr.x = m.x;
        if (use_map_rough > 0) fr.y = m.y;
    }
    if (n_dots > 0) {
        float fw = max(length(fwidth(v_pos)), 1e-6);
        float cover = 0.0;
        int which = 0;
        // a dot covers this fragment only within radius + fw / 2 of its centre, and the fragment lies within
        // fw / 2 of its triangle (the pixel centre of a partly covered pixel): the candidates hold every such
        // dot while fw < dot_margin; else (grazing triangles, too many candidates) all dots are tried
        bool every = v_dots.x == -2 || fw >= dot_margin;
        for (int k = 0; k < (every ? n_dots : 4); k++) {
            int i = every ? k : v_dots[k];
            if (i < 0) break;
            vec4 d = texelFetch(dots, ivec2(i, 0), 0);
            float ci = clamp((d.w - length(v_pos - d.xyz)) / fw + 0.5, 0.0, 1.0);
            if (ci > cover) { cover = ci; which = i; }
        }
        a = mix(a, texelFetch(dots, ivec2(which, 1), 0).rgb, cover);
        if (dot_mat.x >= 0.0) fr.x = mix(fr.x, dot_mat.x, cover);
        if (dot_mat.y >= 0.0) fr.y = mix(fr.y, dot_mat.y, cover);
    }
    vec3 rho = srgb2lin(clamp(a, 0.0, 1.0));
    vec3 v = -normalize(v_pos);
    float nv = clamp(dot(n, v), 1e-4, 1.0);
    float al = max(fr.y, 0.02);
    al *= al;
    float a2 = al * al;
    vec3 L = vec3(0.0);
    for (int i = 0; i < n_lights; i++) {
        if (l_kind[i] == 0) { L += rho * l_rad[i]; continue; }
        vec3 l;
        vec3 E;
        if (l_kind[i] == 1) { l = l_vec[i]; E = l_rad[i]; }
        else {
            vec3 d = l_vec[i] - v_pos;
            float d2 = dot(d, d);
            l = d * inversesqrt(d2);
            E = l_rad[i] * (l_ref2[i] / d2);
        }
        float nl = dot(n, l);
        if (nl <= 0.0) continue;
        float vis = l_smap[i] >= 0 ? visibility(l_smap[i], v_pos, nl, l_soft[i]) : 1.0;
        vec3 h = normalize(l + v);
        float nh = clamp(dot(n, h), 0.0, 1.0);
        float vh = clamp(dot(v, h), 0.0, 1.0);
        float dd = nh * nh * (a2 - 1.0) + 1.0;
        float D = a2 / (PI * dd * dd);
        float nlc = max(nl, 1e-4);
        float Vis = 0.5 / (nlc * sqrt(nv * nv * (1.0 - a2) + a2) + nv * sqrt(nlc * nlc * (1.0 - a2) + a2));
        float F = fr.x + (1.0 - fr.x) * pow(1.0 - vh, 5.0);
        L += E * (nl * vis) * ((1.0 - F) * rho + PI * D * Vis * F);
    }
    out_color = vec4(L, 1.0);
}
"""
_SHADOW_VS = """
#version 330
uniform mat4 s_view_m;
uniform mat4 s_clip;
in vec3 in_pos;
out float v_z;
void main() {
    vec4 q = s_view_m * vec4(in_pos, 1.0);
    v_z = q.z;
    gl_Position = s_clip * q;
}
"""
_SHADOW_FS = """
#version 330
in float v_z;
out float o_z;
void main() { o_z = v_z; }
"""
_RESOLVE_VS = """
#version 400
in vec2 in_xy;
void main() { gl_Position = vec4(in_xy, 0.0, 1.0); }
"""
# Exact visibility at distorted pixel centres: the pixel's ray (x, y, 1) is intersected (in double
# precision) with the triangles found at the 2x2 pinhole pixel centres around its pinhole position.
_RESOLVE_FS = """
#version 400
uniform isampler2D pin_ids;   // pinhole triangle id + 1, 0 = background
uniform sampler2D rays;       // RG32F per distorted pixel: normalized (x, y)
uniform sampler2D tris;       // RGB32F: corner k of triangle f at texel 3 f + k (row-major, width tw)
uniform int tw_mask;          // texture width - 1 (width is a power of two)
uniform int tw_shift;         // log2(texture width)
uniform dvec3 kp_row0;        // pinhole fx, skew, cx
uniform dvec2 kp_row1;        // pinhole fy, cy
uniform ivec2 pin_size;
uniform double tol;
uniform double disc_mm;       // candidate plane depths further apart than this mark an occlusion boundary
layout(location = 0) out float o_depth;
layout(location = 1) out int o_id;      // triangle id, -1 background, -2 needs a neighbourhood search
layout(location = 2) out vec4 o_bary;

dvec3 corner(int i) { return dvec3(texelFetch(tris, ivec2(i & tw_mask, i >> tw_shift), 0).xyz); }

// Intersect the ray (x, y, 1) with triangle f; returns (z, b1, b2) with b0 = 1 - b1 - b2.
dvec3 intersect(int f, dvec3 d) {
    dvec3 A = corner(3 * f), e1 = corner(3 * f + 1) - A, e2 = corner(3 * f + 2) - A;
    dvec3 p = cross(d, e2);
    double det = dot(e1, p);
    if (det == 0.0) return dvec3(-1.0, -1.0, -1.0);
    dvec3 q = cross(-A, e1);
    return dvec3(dot(e2, q), -dot(A, p), dot(d, q)) / det;
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    dvec2 xy = dvec2(texelFetch(rays, px, 0).xy);
    double mx = kp_row0.x * xy.x + kp_row0.y * xy.y + kp_row0.z;
    double my = kp_row1.x * xy.y + kp_row1.y;
    ivec2 p0 = clamp(ivec2(floor(vec2(mx, my))), ivec2(0), pin_size - 2);
    ivec4 c = ivec4(texelFetch(pin_ids, p0, 0).x, texelFetch(pin_ids, p0 + ivec2(1, 0), 0).x,
                    texelFetch(pin_ids, p0 + ivec2(0, 1), 0).x, texelFetch(pin_ids, p0 + ivec2(1, 1), 0).x) - 1;
    dvec3 d = dvec3(xy, 1.0);
    if (all(equal(c, ivec4(-1)))) {
        o_id = -1; o_depth = 0.0; o_bary = vec4(0.0);
        return;
    }
    if (all(equal(c, c.xxxx))) {            // a projected triangle is convex: it is the one
        dvec3 h = intersect(c.x, d);
        o_id = c.x; o_depth = float(h.x); o_bary = vec4(float(1.0 - h.y - h.z), float(h.y), float(h.z), 0.0);
        return;
    }
    double best_z = 1e300, plane_min = 1e300, plane_max = -1e300;
    int best = -1;
    dvec3 best_b = dvec3(0.0);
    for (int k = 0; k < 4; k++) {
        int f = c[k];
        if (f < 0) continue;
        dvec3 h = intersect(f, d);
        plane_min = min(plane_min, h.x);
        plane_max = max(plane_max, h.x);
        dvec3 b = dvec3(1.0 - h.y - h.z, h.y, h.z);
        if (min(b.x, min(b.y, b.z)) >= -tol && h.x > 0.0 && h.x < best_z) { best_z = h.x; best = f; best_b = b; }
    }
    o_id = best >= 0 ? best : -2;
    o_depth = best >= 0 ? float(best_z) : 0.0;
    // w = 1: an occlusion boundary (candidate planes far apart along the ray): a nearer sliver may hide
    // between the pinhole pixel centres, so the candidates' neighbours get searched too
    bool boundary = plane_max - plane_min > disc_mm;
    o_bary = vec4(vec3(best_b), (best >= 0 && boundary) ? 1.0 : 0.0);
}
"""


class _GL:
    """The process-wide EGL context with compiled programs and caches (created lazily)."""

    def __init__(self) -> None:
        import moderngl

        self.moderngl = moderngl
        self.ctx = moderngl.create_standalone_context(backend="egl")
        self.id_prog = self.ctx.program(vertex_shader=_ID_VS, fragment_shader=_ID_FS)
        self.color_prog = self.ctx.program(vertex_shader=_COLOR_VS, fragment_shader=_COLOR_FS)
        self.resolve_prog = self.ctx.program(vertex_shader=_RESOLVE_VS, fragment_shader=_RESOLVE_FS)
        tri = np.array([-1.0, -1.0, 3.0, -1.0, -1.0, 3.0], dtype="f4")
        self.fullscreen_vbo = self.ctx.buffer(tri.tobytes())
        self.fullscreen_vao = self.ctx.vertex_array(self.resolve_prog, [(self.fullscreen_vbo, "2f", "in_xy")])
        self._fbos: dict[tuple, tuple] = {}
        self._resolve_fbos: dict[tuple, object] = {}
        self._rays: dict[tuple, object] = {}
        self._textures: dict[int, tuple] = {}
        self._progs: dict[str, object] = {}
        self._shadow_fbos: dict[tuple, tuple] = {}
        self._dummy = None

    def program(self, name: str):
        """A lazily compiled shader program: ``"dot_colors"``, ``"lit"`` or ``"shadow"``."""
        prog = self._progs.get(name)
        if prog is None:
            vs, fs = {"dot_colors": (_COLOR_VS, _COLOR_FS_DOT_COLORS), "lit": (_LIT_VS, _LIT_FS),
                      "shadow": (_SHADOW_VS, _SHADOW_FS)}[name]
            prog = self.ctx.program(vertex_shader=vs, fragment_shader=fs)
            self._progs[name] = prog
        return prog

    def shadow_framebuffer(self, size: int, index: int):
        """(framebuffer, R32F texture) number ``index`` of side ``size`` for a shadow map; cached."""
        key = (size, index)
        hit = self._shadow_fbos.get(key)
        if hit is None:
            tex = self.ctx.texture((size, size), 1, dtype="f4")
            tex.filter = (self.moderngl.NEAREST, self.moderngl.NEAREST)
            fbo = self.ctx.framebuffer(color_attachments=[tex], depth_attachment=self.ctx.depth_renderbuffer((size, size)))
            hit = (fbo, tex)
            self._shadow_fbos[key] = hit
        return hit

    def dummy_texture(self):
        """A 1x1 float texture bound to unused sampler units."""
        if self._dummy is None:
            self._dummy = self.ctx.texture((1, 1), 3, np.zeros(3, "f4").tobytes(), dtype="f4")
        return self._dummy

    def float_texture(self, image: np.ndarray):
        """GL texture (mipmapped, repeat) of an (H, W, 3) float32 image, cached per array (material maps)."""
        def upload(img):
            data = np.ascontiguousarray(img[::-1], dtype="f4")
            return self.ctx.texture((img.shape[1], img.shape[0]), 3, data.tobytes(), dtype="f4")

        return self._cached_texture(image, upload, anisotropic=False)

    # ------------------------------------------------------------------ caches
    def texture(self, image: np.ndarray):
        """GL texture (mipmapped, anisotropic, repeat) of an (H, W, 3) uint8 image, cached per array."""
        def upload(img):
            data = np.ascontiguousarray(img[::-1])  # GL row 0 = texture v = 0 = bottom image row (OBJ)
            return self.ctx.texture((img.shape[1], img.shape[0]), 3, data.tobytes(), alignment=1)

        return self._cached_texture(image, upload, anisotropic=True)

    def _cached_texture(self, image: np.ndarray, upload, anisotropic: bool):
        """The texture ``upload(image)`` made for this very array (mipmapped, repeat), cached while it lives."""
        dead = [k for k, (ref, _) in self._textures.items() if ref() is None]
        for k in dead:
            self._textures.pop(k)[1].release()
        hit = self._textures.get(id(image))
        if hit is not None and hit[0]() is image:
            return hit[1]
        tex = upload(image)
        tex.build_mipmaps()
        tex.filter = (self.moderngl.LINEAR_MIPMAP_LINEAR, self.moderngl.LINEAR)
        if anisotropic:
            tex.anisotropy = min(ANISOTROPY, self.ctx.max_anisotropy)
        tex.repeat_x = tex.repeat_y = True
        self._textures[id(image)] = (weakref.ref(image), tex)
        return tex

    def rays_texture(self, camera: Camera):
        """RG32F texture of the normalized ray coordinates of every distorted pixel; cached per camera."""
        key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes())
        tex = self._rays.get(key)
        if tex is None:
            xy = np.ascontiguousarray(pixel_rays(camera), dtype="f4")
            tex = self.ctx.texture((camera.width, camera.height), 2, xy.tobytes(), dtype="f4")
            tex.filter = (self.moderngl.NEAREST, self.moderngl.NEAREST)
            if len(self._rays) >= 16:
                self._rays.pop(next(iter(self._rays))).release()
            self._rays[key] = tex
        return tex

    def resolve_framebuffer(self, width: int, height: int):
        """Framebuffer with depth (R32F), id (R32I) and barycentric (RGBA32F) targets; cached per size."""
        key = (width, height)
        fbo = self._resolve_fbos.get(key)
        if fbo is None:
            ctx = self.ctx
            size = (width, height)
            fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 1, dtype="f4"),
                                                     ctx.renderbuffer(size, 1, dtype="i4"),
                                                     ctx.renderbuffer(size, 4, dtype="f4")])
            if len(self._resolve_fbos) >= 8:
                self._resolve_fbos.pop(next(iter(self._resolve_fbos))).release()
            self._resolve_fbos[key] = fbo
        return fbo

    def framebuffers(self, width: int, height: int, msaa: bool):
        """(id_fbo, color_fbo, resolve_fbo or None) for a pinhole image size; cached."""
        key = (width, height, msaa)
        if key not in self._fbos:
            ctx = self.ctx
            size = (width, height)
            id_fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 1, dtype="i4")],
                                     depth_attachment=ctx.depth_renderbuffer(size))
            if msaa:
                color = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4, samples=MSAA_SAMPLES, dtype="f4")],
                                        depth_attachment=ctx.depth_renderbuffer(size, samples=MSAA_SAMPLES))
                resolve = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4, dtype="f4")])
            else:
                color = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4, dtype="f4")],
                                        depth_attachment=ctx.depth_renderbuffer(size))
                resolve = None
            if len(self._fbos) >= 8:
                for obj in self._fbos.pop(next(iter(self._fbos))):
                    if obj is not None:
                        obj.release()
            self._fbos[key] = (id_fbo, color, resolve)
        return self._fbos[key]


_STATE: dict[str, object] = {}


def gl_context() -> _GL:
    """The cached EGL renderer state of this process (created on first use; raises if EGL is absent)."""
    st = _STATE.get("gl")
    if st is None:
        err = _STATE.get("error")
        if err is not None:
            raise RuntimeError(f"EGL context unavailable: {err}")
        try:
            st = _GL()
        except Exception as exc:  # noqa: BLE001 - any failure means "no EGL here"
            _STATE["error"] = repr(exc)
            raise RuntimeError(f"EGL context unavailable: {exc!r}") from exc
        _STATE["gl"] = st
    return st  # type: ignore[return-value]


def egl_available() -> bool:
    """True if a standalone EGL context can be created in this process."""
    try:
        gl_context()
        return True
    except RuntimeError:
        return False


# ------------------------------------------------------------------ geometry helpers
_COVER_CACHE: dict[tuple, tuple] = {}


def pinhole_cover(camera: Camera, margin: int = PINHOLE_MARGIN_PX):
    """Pinhole image covering the distorted image. Cached per intrinsics, size and margin (read-only arrays).

    Returns
    -------
    Kp : (3, 3) pinhole intrinsics (same focal lengths/skew, shifted principal point).
    size : (Wp, Hp) pinhole image size.
    map_x, map_y : (H, W) float32 pinhole pixel coordinates of each distorted pixel centre.
    xy : (H, W, 2) float64 normalized ray coordinates of each distorted pixel centre.
    """
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), int(margin))
    hit = _COVER_CACHE.get(key)
    if hit is None:
        hit = _pinhole_cover(camera, margin)
        for a in (hit[0], *hit[2:]):
            a.setflags(write=False)
        if len(_COVER_CACHE) >= 16:
            _COVER_CACHE.pop(next(iter(_COVER_CACHE)))
        _COVER_CACHE[key] = hit
    return hit


def _pinhole_cover(camera: Camera, margin: int):
    xy = pixel_rays(camera)
    K = camera.K
    valid = _invertible_pixels(camera, xy)
    if not valid.all():
        # a fitted distortion polynomial can fold over near the image corners (a calibration that
        # extrapolates): those pixels have no ray; they render as background
        xy = np.where(valid[..., None], xy, np.nan)
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    ox = margin - np.floor(np.nanmin(u))
    oy = margin - np.floor(np.nanmin(v))
    Wp = int(np.ceil(np.nanmax(u) + ox)) + margin + 1
    Hp = int(np.ceil(np.nanmax(v) + oy)) + margin + 1
    if Wp > 3 * camera.width or Hp > 3 * camera.height:
        raise ValueError(f"camera {camera.id}: distortion too strong to render (pinhole cover {Wp}x{Hp})")
    Kp = K.copy()
    Kp[0, 2] += ox
    Kp[1, 2] += oy
    map_x = np.nan_to_num((u + ox).astype(np.float32), nan=-1e6)
    map_y = np.nan_to_num((v + oy).astype(np.float32), nan=-1e6)
    return Kp, (Wp, Hp), map_x, map_y, xy


def _invertible_pixels(camera: Camera, xy: np.ndarray, tol_px: float = 0.05) -> np.ndarray:
    """(H, W) bool: pixels whose undistorted ray distorts back onto the pixel (within ``tol_px``) and
    lies where the radial distortion is still monotonic."""
    from rigbuild.camera import distort_normalized

    H, W = camera.height, camera.width
    xd, yd = distort_normalized(xy[..., 0], xy[..., 1], camera.dist)
    K = camera.K
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    gu, gv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    ok = np.hypot(u - gu, v - gv) < tol_px
    k1, k2, _, _, k3 = camera.dist
    r2 = (xy ** 2).sum(-1)
    # d(r * (1 + k1 r^2 + k2 r^4 + k3 r^6)) / dr > 0
    ok &= 1 + 3 * k1 * r2 + 5 * k2 * r2 ** 2 + 7 * k3 * r2 ** 3 > 0
    return ok & np.isfinite(r2)


def gl_projection(Kp: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """(4, 4) GL clip matrix for camera-frame points (OpenCV axes) and pinhole intrinsics ``Kp``.

    Pixel centre ``(u, v)`` maps to window coordinates ``(u + 0.5, v + 0.5)``; depth range [near, far] mm.
    """
    fx, s, cx = Kp[0]
    fy, cy = Kp[1, 1], Kp[1, 2]
    P = np.zeros((4, 4))
    P[0] = [2 * fx / width, 2 * s / width, 2 * (cx + 0.5) / width - 1, 0]
    P[1] = [0, 2 * fy / height, 2 * (cy + 0.5) / height - 1, 0]
    P[2] = [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)]
    P[3] = [0, 0, 1, 0]
    return P


def _near_far(z: np.ndarray) -> tuple[float, float]:
    zmax = float(np.max(z)) if z.size else 1.0
    zpos = z[z > 0]
    zmin = float(zpos.min()) if zpos.size else 1.0
    near = max(0.5 * zmin, 1e-3 * max(zmax, 1.0), 1e-3)
    far = max(2.0 * zmax, near * 2.0)
    return near, far


# ------------------------------------------------------------------ public
def render_mesh(camera: Camera, mesh: TexturedMesh, opt: RenderOptions) -> RenderResult:
    """Render ``mesh`` seen by ``camera`` (with its lens distortion) by rasterization on EGL/llvmpipe.

    ``opt`` : :class:`rigbuild.render.common.RenderOptions` (documented at :func:`rigbuild.render.render_mesh`);
    ``opt.msaa`` multisamples the colour pass (depth/id/bary never multisample); ``opt.with_motion`` runs the
    geometry pass even when ``opt.with_geometry`` is False.

    Returns
    -------
    :class:`RenderResult` (colour, depth mm, triangle id, barycentrics), exact at OpenCV pixel centres.
    """
    gl = gl_context()
    ctx = gl.ctx
    Kp, (Wp, Hp), map_x, map_y, xy = pinhole_cover(camera)
    if mesh.faces.shape[0] == 0:
        return empty_result(camera, mesh, opt)
    light_dir, ambient, background, msaa = opt.light_dir, opt.ambient, opt.background, opt.msaa
    noise_sigma, seed = opt.noise_sigma, opt.seed
    with_color, with_geometry, lights, material = opt.with_color, opt.with_geometry, opt.lights, opt.material
    output, with_motion = opt.output, opt.with_motion
    if output not in ("srgb8", "linear", "both"):
        raise ValueError(f"render output must be 'srgb8', 'linear' or 'both', got {output!r}")
    with_geometry = with_geometry or with_motion

    V = camera.world_to_camera(mesh.vertices)
    tri_cam = V[mesh.faces]  # (F, 3, 3) float64
    N = mesh.normals() @ camera.R.T
    near, far = _near_far(V[:, 2])
    proj = gl_projection(Kp, Wp, Hp, near, far).T.astype("f4").tobytes()  # column-major
    bg = background_rgb(background)

    corners = mesh.faces.reshape(-1)
    pos = np.ascontiguousarray(V[corners], dtype="f4")
    id_fbo, color_fbo, resolve_fbo = gl.framebuffers(Wp, Hp, msaa)
    ctx.enable(ctx.DEPTH_TEST)
    ctx.disable(ctx.CULL_FACE)

    buffers = []
    try:
        vbo_pos = ctx.buffer(pos.tobytes())
        buffers.append(vbo_pos)
        pin_ids = None
        if with_geometry:  # ---- id pass
            gl.id_prog["proj"].write(proj)
            vao_id = ctx.vertex_array(gl.id_prog, [(vbo_pos, "3f", "in_pos")])
            buffers.append(vao_id)
            id_fbo.use()
            id_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            vao_id.render(gl.moderngl.TRIANGLES)
            pin_ids = np.frombuffer(id_fbo.read(components=1, dtype="i4"), dtype=np.int32).reshape(Hp, Wp)
        # ---- colour pass
        pin_rgb = None
        if with_color and lights is None:
            pin_rgb = _color_pass(gl, camera, mesh, N[corners], vbo_pos, proj, light_dir, ambient, bg,
                                  color_fbo, resolve_fbo, buffers)
        elif with_color:
            bg = srgb_to_linear(bg / 255.0).astype(np.float64)
            pin_rgb = _lit_color_pass(gl, camera, mesh, V, N[corners], vbo_pos, proj, lights, material, bg,
                                      color_fbo, resolve_fbo, buffers)
        elif lights is not None:
            bg = srgb_to_linear(bg / 255.0).astype(np.float64)
    finally:
        for b in buffers:
            b.release()

    import cv2

    if pin_rgb is None:
        color = np.broadcast_to(bg.astype(np.float32), (camera.height, camera.width, 3))
    else:
        color = cv2.remap(pin_rgb, map_x, map_y, interpolation=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=tuple(bg.tolist()))
    if with_geometry:
        depth, tri_id, bary = _resolve_gl(gl, camera, Kp, pin_ids, tri_cam, mesh.faces, map_x, map_y, xy)
    else:
        H, W = camera.height, camera.width
        depth = np.full((H, W), np.nan, np.float32)
        tri_id = np.full((H, W), -1, np.int32)
        bary = np.zeros((H, W, 3), np.float32)
    res = RenderResult(None if lights is not None else finish_color(color, noise_sigma, camera, seed),
                       depth, tri_id, bary)
    return finish_outputs(res, color, lights, output, noise_sigma, camera, seed, with_motion, mesh)


def _color_pass(gl: _GL, camera: Camera, mesh: TexturedMesh, normals_cam, vbo_pos, proj: bytes, light_dir,
                ambient: float, bg: np.ndarray, color_fbo, resolve_fbo, buffers: list) -> np.ndarray:
    """Shade the pinhole image: (Hp, Wp, 3) float32 in 8-bit levels. GL objects made here go to ``buffers``."""
    ctx = gl.ctx
    nrm = np.ascontiguousarray(normals_cam, dtype="f4")
    uv = np.ascontiguousarray(mesh.uvs[mesh.face_uvs.reshape(-1)], dtype="f4")
    vbo_n = ctx.buffer(nrm.tobytes())
    vbo_uv = ctx.buffer(uv.tobytes())
    buffers += [vbo_n, vbo_uv]
    prog = gl.program("dot_colors") if mesh.per_dot_albedo else gl.color_prog
    prog["proj"].write(proj)
    prog["light_dir"].value = tuple(float(x) for x in light_in_camera(camera, light_dir))
    prog["ambient"].value = float(ambient)
    if not mesh.per_dot_albedo:
        prog["dot_albedo"].value = tuple(float(c) / 255.0 for c in np.broadcast_to(mesh.dot_albedo, (3,)))
    prog["albedo"].value = 0
    prog["dots"].value = 1
    gl.texture(mesh.texture).use(location=0)
    n_dots = 0 if mesh.dot_centers is None else mesh.dot_centers.shape[0]
    dots = _dots_array(camera, mesh) if mesh.per_dot_albedo else np.zeros((max(n_dots, 1), 4), dtype="f4")
    if n_dots and not mesh.per_dot_albedo:
        dots[:, :3] = camera.world_to_camera(mesh.dot_centers)
        dots[:, 3] = mesh.dot_radii
    rows = 2 if mesh.per_dot_albedo else 1
    dots_tex = ctx.texture((dots.shape[0] // rows, rows), 4, dots.tobytes(), dtype="f4")
    dots_tex.filter = (gl.moderngl.NEAREST, gl.moderngl.NEAREST)
    buffers.append(dots_tex)
    dots_tex.use(location=1)
    prog["n_dots"].value = int(n_dots)
    vao_c = ctx.vertex_array(prog, [(vbo_pos, "3f", "in_pos"), (vbo_n, "3f", "in_normal"), (vbo_uv, "2f", "in_uv")])
    buffers.append(vao_c)
    color_fbo.use()
    color_fbo.clear(*bg.tolist(), 1.0, depth=1.0)  # float buffer in 0..255 levels
    vao_c.render(gl.moderngl.TRIANGLES)
    src = color_fbo
    if resolve_fbo is not None:
        ctx.copy_framebuffer(resolve_fbo, color_fbo)
        src = resolve_fbo
    Wp, Hp = src.size
    return np.frombuffer(src.read(components=3, dtype="f4"), dtype=np.float32).reshape(Hp, Wp, 3)


def _dots_array(camera: Camera, mesh: TexturedMesh) -> np.ndarray:
    """(2 * max(M, 1), 4) float32 dots texture: row 0 centres (camera frame, mm) and radii, row 1 RGB 0..1."""
    M = 0 if mesh.dot_centers is None else mesh.dot_centers.shape[0]
    dots = np.zeros((2, max(M, 1), 4), dtype="f4")
    if M:
        dots[0, :, :3] = camera.world_to_camera(mesh.dot_centers)
        dots[0, :, 3] = mesh.dot_radii
        dots[1, :, :3] = mesh.dot_colors() / np.float32(255.0)
    return dots.reshape(-1, 4)


def ortho_projection(frame, near: float, far: float) -> np.ndarray:
    """(4, 4) GL clip matrix of an orthographic shadow frame (texel centre ``u`` -> window ``u + 0.5``)."""
    S = frame.size
    P = np.zeros((4, 4))
    P[0] = [2 * frame.a / S, 0, 0, 2 * (frame.cu + 0.5) / S - 1]
    P[1] = [0, 2 * frame.a / S, 0, 2 * (frame.cv + 0.5) / S - 1]
    P[2] = [0, 0, 2 / (far - near), -(far + near) / (far - near)]
    P[3] = [0, 0, 0, 1]
    return P


def _shadow_pass(gl: _GL, frame, vbo_pos, index: int, buffers: list):
    """Render the light-frame depth of the mesh into shadow map ``index``; returns its texture."""
    ctx = gl.ctx
    prog = gl.program("shadow")
    view = np.eye(4)
    view[:3, :3] = frame.R
    view[:3, 3] = frame.t
    if frame.perspective:
        near = 0.5 * frame.near
        far = 1.5 * frame.far + 1.0
        Kl = np.array([[frame.a, 0.0, frame.cu], [0.0, frame.a, frame.cv], [0.0, 0.0, 1.0]])
        clip = gl_projection(Kl, frame.size, frame.size, near, far)
    else:
        clip = ortho_projection(frame, frame.near - 10.0, frame.far + 10.0)
    prog["s_view_m"].write(view.T.astype("f4").tobytes())
    prog["s_clip"].write(clip.T.astype("f4").tobytes())
    vao = ctx.vertex_array(prog, [(vbo_pos, "3f", "in_pos")])
    buffers.append(vao)
    fbo, tex = gl.shadow_framebuffer(frame.size, index)
    fbo.use()
    fbo.clear(1e30, 1e30, 1e30, 1e30, depth=1.0)
    vao.render(gl.moderngl.TRIANGLES)
    return tex, view


def _set(prog, name: str, value) -> None:
    """Set a uniform if the compiler kept it."""
    try:
        u = prog[name]
    except KeyError:
        return
    u.value = value


def _lit_color_pass(gl: _GL, camera: Camera, mesh: TexturedMesh, V, normals_cam, vbo_pos, proj: bytes, lights,
                    material, bg_lin: np.ndarray, color_fbo, resolve_fbo, buffers: list) -> np.ndarray:
    """Shade the pinhole image in linear light (GGX + Lambert, shadow maps): (Hp, Wp, 3) float32."""
    from rigbuild.render.lights import MAX_LIGHTS, MAX_SHADOW_MAPS, PCF_TAPS, SHADOW_MAP_SIZE, Material

    ctx = gl.ctx
    mat = material if material is not None else Material()
    Ls = lights_in_camera(camera, lights)
    if len(Ls) > MAX_LIGHTS:
        raise ValueError(f"render_mesh: at most {MAX_LIGHTS} lights, got {len(Ls)}")
    if sum(L["shadows"] for L in Ls) > MAX_SHADOW_MAPS:
        raise ValueError(f"render_mesh: at most {MAX_SHADOW_MAPS} shadowing lights")
    prog = gl.program("lit")
    # ---- shadow maps
    smaps, views, projs, idx = [], [], [], []
    for L in Ls:
        if not L["shadows"]:
            idx.append(-1)
            continue
        frame = shadow_frame(L, V, SHADOW_MAP_SIZE)
        tex, view = _shadow_pass(gl, frame, vbo_pos, len(smaps), buffers)
        idx.append(len(smaps))
        smaps.append(tex)
        views.append(view)
        projs.append((frame.a, frame.cu, frame.cv, 1.0 if frame.perspective else 0.0))
    # ---- colour
    corners = mesh.faces.reshape(-1)
    nrm = np.ascontiguousarray(normals_cam, dtype="f4")
    uv = np.ascontiguousarray(mesh.uvs[mesh.face_uvs.reshape(-1)], dtype="f4")
    fr = np.ascontiguousarray(mat.vertex_values(mesh.vertices.shape[0])[corners], dtype="f4")
    dots = _dots_array(camera, mesh)
    n_dots = 0 if mesh.dot_centers is None else mesh.dot_centers.shape[0]
    cand = np.full((mesh.faces.shape[0], DOT_CANDIDATES), -1, dtype=np.int32)
    if n_dots:
        cand = dot_candidates(V[mesh.faces], dots[:n_dots, :3], dots[:n_dots, 3], DOT_MARGIN_MM)
    cand = np.ascontiguousarray(np.repeat(cand, 3, axis=0), dtype="i4")  # one row per corner
    vbo_n, vbo_uv, vbo_m = ctx.buffer(nrm.tobytes()), ctx.buffer(uv.tobytes()), ctx.buffer(fr.tobytes())
    vbo_d = ctx.buffer(cand.tobytes())
    buffers += [vbo_n, vbo_uv, vbo_m, vbo_d]
    prog["proj"].write(proj)
    gl.texture(mesh.texture).use(location=0)
    _set(prog, "albedo", 0)
    packed = mat.packed_map(mesh.texture.shape[:2])
    (gl.float_texture(packed) if packed is not None else gl.dummy_texture()).use(location=1)
    _set(prog, "matmap", 1)
    use_s, use_r = mat.has_maps
    _set(prog, "use_map_f0", int(use_s))
    _set(prog, "use_map_rough", int(use_r))
    dots_tex = ctx.texture((dots.shape[0] // 2, 2), 4, dots.tobytes(), dtype="f4")
    dots_tex.filter = (gl.moderngl.NEAREST, gl.moderngl.NEAREST)
    buffers.append(dots_tex)
    dots_tex.use(location=2)
    _set(prog, "dots", 2)
    _set(prog, "n_dots", int(n_dots))
    _set(prog, "dot_margin", float(DOT_MARGIN_MM))
    _set(prog, "dot_mat", (-1.0 if mat.dot_specular is None else float(mat.dot_specular),
                           -1.0 if mat.dot_roughness is None else float(mat.dot_roughness)))
    pad = MAX_LIGHTS - len(Ls)
    _set(prog, "n_lights", len(Ls))
    _set(prog, "l_kind", [int(L["kind"]) for L in Ls] + [0] * pad)
    _set(prog, "l_vec", [tuple(float(x) for x in L["vec"]) for L in Ls] + [(0.0, 0.0, 0.0)] * pad)
    _set(prog, "l_rad", [tuple(float(x) for x in L["rad"]) for L in Ls] + [(0.0, 0.0, 0.0)] * pad)
    _set(prog, "l_ref2", [float(L["ref2"]) for L in Ls] + [1.0] * pad)
    _set(prog, "l_smap", idx + [-1] * pad)
    _set(prog, "l_soft", [float(L["softness"]) for L in Ls] + [0.0] * pad)
    for k in range(MAX_SHADOW_MAPS):
        (smaps[k] if k < len(smaps) else gl.dummy_texture()).use(location=3 + k)
    _set(prog, "smap", list(range(3, 3 + MAX_SHADOW_MAPS)))
    spad = MAX_SHADOW_MAPS - len(smaps)
    mats = np.stack([(views[k] if k < len(views) else np.eye(4)).T for k in range(MAX_SHADOW_MAPS)])
    if "s_view" in prog:
        prog["s_view"].write(np.ascontiguousarray(mats, dtype="f4").tobytes())
    _set(prog, "s_proj", projs + [(1.0, 0.0, 0.0, 0.0)] * spad)
    _set(prog, "s_size", int(SHADOW_MAP_SIZE))
    _set(prog, "taps", [tuple(float(x) for x in t) for t in vogel_taps(PCF_TAPS)])
    vao_c = ctx.vertex_array(prog, [(vbo_pos, "3f", "in_pos"), (vbo_n, "3f", "in_normal"), (vbo_uv, "2f", "in_uv"),
                                    (vbo_m, "2f", "in_mat"), (vbo_d, "4i", "in_dots")])
    buffers.append(vao_c)
    color_fbo.use()
    color_fbo.clear(*bg_lin.tolist(), 1.0, depth=1.0)
    vao_c.render(gl.moderngl.TRIANGLES)
    src = color_fbo
    if resolve_fbo is not None:
        ctx.copy_framebuffer(resolve_fbo, color_fbo)
        src = resolve_fbo
    Wp, Hp = src.size
    return np.frombuffer(src.read(components=3, dtype="f4"), dtype=np.float32).reshape(Hp, Wp, 3)


TRI_TEXTURE_WIDTH = 4096


def _resolve_gl(gl: _GL, camera: Camera, Kp, pin_ids, tri_cam, faces, map_x, map_y, xy, rings: int = 2):
    """Exact depth/id/bary at the distorted pixel centres (GLSL pass, then a numpy neighbourhood search
    for the few pixels whose 2x2 candidates all miss or straddle an occlusion boundary)."""
    ctx = gl.ctx
    W, H = camera.width, camera.height
    Hp, Wp = pin_ids.shape
    F = tri_cam.shape[0]
    tw = TRI_TEXTURE_WIDTH
    rows = max(1, -(-3 * F // tw))
    corners = np.zeros((rows * tw, 3), dtype="f4")
    corners[: 3 * F] = tri_cam.reshape(-1, 3)
    released = []
    try:
        tris = ctx.texture((tw, rows), 3, corners.tobytes(), dtype="f4")
        ids_tex = ctx.texture((Wp, Hp), 1, np.ascontiguousarray(pin_ids).tobytes(), dtype="i4")
        released += [tris, ids_tex]
        for t in (tris, ids_tex):
            t.filter = (gl.moderngl.NEAREST, gl.moderngl.NEAREST)
        prog = gl.resolve_prog
        ids_tex.use(location=0)
        gl.rays_texture(camera).use(location=1)
        tris.use(location=2)
        prog["pin_ids"].value = 0
        prog["rays"].value = 1
        prog["tris"].value = 2
        prog["tw_mask"].value = tw - 1
        prog["tw_shift"].value = int(np.log2(tw))
        prog["kp_row0"].value = (float(Kp[0, 0]), float(Kp[0, 1]), float(Kp[0, 2]))
        prog["kp_row1"].value = (float(Kp[1, 1]), float(Kp[1, 2]))
        prog["pin_size"].value = (Wp, Hp)
        prog["tol"].value = 1e-7
        prog["disc_mm"].value = 1.0
        fbo = gl.resolve_framebuffer(W, H)
        fbo.use()
        ctx.disable(ctx.DEPTH_TEST)
        gl.fullscreen_vao.render(gl.moderngl.TRIANGLES)
        ctx.enable(ctx.DEPTH_TEST)
        depth = np.frombuffer(fbo.read(components=1, attachment=0, dtype="f4"), dtype=np.float32).reshape(H, W).copy()
        tri_id = np.frombuffer(fbo.read(components=1, attachment=1, dtype="i4"), dtype=np.int32).reshape(H, W).copy()
        bary4 = np.frombuffer(fbo.read(components=4, attachment=2, dtype="f4"), dtype=np.float32).reshape(H, W, 4)
        bary = bary4[..., :3].copy()
        boundary = bary4[..., 3] > 0.5
    finally:
        for t in released:
            t.release()
    # pixels whose 2x2 candidates all miss, and resolved pixels on occlusion boundaries
    todo = np.flatnonzero((tri_id.reshape(-1) == -2) | boundary.reshape(-1))
    tri_id[tri_id == -2] = -1
    if todo.size and rings > 0:
        mx, my = map_x.reshape(-1)[todo], map_y.reshape(-1)[todo]
        i0 = np.clip(np.floor(mx).astype(np.int64), 0, Wp - 2)
        j0 = np.clip(np.floor(my).astype(np.int64), 0, Hp - 2)
        cand = np.stack([pin_ids[j0, i0], pin_ids[j0, i0 + 1], pin_ids[j0 + 1, i0], pin_ids[j0 + 1, i0 + 1]], 1) - 1
        pix, z, tri, b = ring_search(todo, cand, xy.reshape(-1, 2), tri_cam, faces, rings)
        flat_id, flat_z = tri_id.reshape(-1), depth.reshape(-1)
        better = (flat_id[pix] < 0) | (z < flat_z[pix])
        pix, z, tri, b = pix[better], z[better], tri[better], b[better]
        flat_z[pix] = z
        flat_id[pix] = tri
        bary.reshape(-1, 3)[pix] = b
    bg = tri_id < 0
    depth[bg] = np.nan
    bary[bg] = 0.0
    return depth, tri_id, bary
