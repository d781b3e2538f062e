"""GLSL for robot meshes, shipped as Python strings so a wheel needs no package data.

pyrender compiles shaders from files, so ``shader_dir()`` writes them once per content hash
to the temp directory.
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
from pathlib import Path

ROBOT_VERT = """#version 330 core
// Rigid-pose variant of pyrender's mesh.vert: normals use mat3(M) instead of a per-vertex
// inverse-transpose, which dominates vertex cost on software GL for 100k+ triangle robots.
layout(location = 0) in vec3 position;
layout(location = NORMAL_LOC) in vec3 normal;
layout(location = INST_M_LOC) in mat4 inst_m;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;

out vec3 frag_position;
out vec3 frag_normal;

void main()
{
    vec4 world = M * (inst_m * vec4(position, 1.0));
    gl_Position = P * (V * world);
    frag_position = world.xyz;
    frag_normal = mat3(M) * (mat3(inst_m) * normal);
}
"""

ROBOT_FRAG = """#version 330 core
// Cheap stand-in for pyrender's metallic-roughness shader: Lambert diffuse plus normalised
// Blinn-Phong specular from directional lights, same uniforms, same ambient and gamma, so the
// look matches while costing a fraction on software GL.
struct DirectionalLight {
    vec3 color;
    float intensity;
    vec3 direction;
};

struct Material {
    vec3 emissive_factor;
    vec4 base_color_factor;
    float metallic_factor;
    float roughness_factor;
};

uniform Material material;
uniform DirectionalLight directional_lights[MAX_DIRECTIONAL_LIGHTS];
uniform int n_directional_lights;
uniform vec3 cam_pos;
uniform vec3 ambient_light;

in vec3 frag_position;
in vec3 frag_normal;

out vec4 frag_color;

const float PI = 3.141592653589793;

void main()
{
    vec3 base = material.base_color_factor.rgb;
    float metallic = clamp(material.metallic_factor, 0.0, 1.0);
    // Roughness floor: real lights are area lights; a glossy CAD material under our directional
    // lights would otherwise paint mirror-like white streaks along black plastic links.
    float roughness = clamp(material.roughness_factor, 0.4, 1.0);
    float a = roughness * roughness;
    float shininess = max(2.0 / (a * a) - 2.0, 1.0);

    vec3 n = normalize(frag_normal);
    vec3 v = normalize(cam_pos - frag_position);
    if (dot(n, v) < 0.0) n = -n;  // two-sided lighting: CAD meshes have open or flipped patches

    vec3 c_diff = base * (1.0 - 0.04) * (1.0 - metallic);
    vec3 f0 = mix(vec3(0.04), base, metallic);

    vec3 color = base * ambient_light;
    for (int i = 0; i < n_directional_lights; i++) {
        vec3 l = -normalize(directional_lights[i].direction);
        float nl = max(dot(n, l), 0.0);
        vec3 h = normalize(l + v);
        float spec = pow(max(dot(n, h), 0.0), shininess) * (shininess + 8.0) / (8.0 * PI);
        vec3 radiance = directional_lights[i].intensity * directional_lights[i].color;
        color += nl * radiance * (c_diff / PI + f0 * spec);
    }
    color += material.emissive_factor;
    // alpha carries the part (the renderer sets 1 on hand links, ARM_ALPHA on arm links):
    // meshes are drawn opaque (blend ONE, ZERO), so it reaches the read-back untouched
    frag_color = clamp(vec4(pow(color, vec3(1.0 / 2.2)), material.base_color_factor.a), 0.0, 1.0);
}
"""

SOURCES = {"robot.vert": ROBOT_VERT, "robot.frag": ROBOT_FRAG}


@functools.lru_cache(maxsize=1)
def shader_dir() -> Path:
    """Directory holding ``robot.vert`` and ``robot.frag`` (written atomically if missing)."""
    digest = hashlib.sha1("".join(SOURCES.values()).encode()).hexdigest()[:12]
    d = Path(tempfile.gettempdir()) / f"handedit-shaders-{digest}"
    d.mkdir(parents=True, exist_ok=True)
    for name, text in SOURCES.items():
        path = d / name
        if not path.is_file() or path.read_text() != text:
            tmp = d / f".{name}.{os.getpid()}"
            tmp.write_text(text)
            os.replace(tmp, path)
    return d
