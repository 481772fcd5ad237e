#version 330 core
// Soft stylised shading of the avatar, per vertex (Gouraud): on llvmpipe per-fragment lighting of ~40k
// covered pixels costs more than lighting ~13k vertices, and the soft look needs no per-pixel detail.
// Wrapped Lambert per directional light, a sky/ground hemisphere ambient, a faint Blinn-Phong highlight and
// a view-dependent rim; vertex colours are the albedo. The normal matrix is mat3(M): the models are rigid.
// A primitive without normals (the ground) is unlit: its vertex colours are its final colours.

struct DirectionalLight {
    vec3 direction;
    vec3 color;
    float intensity;
};

layout(location = 0) in vec3 position;
#ifdef NORMAL_LOC
layout(location = NORMAL_LOC) in vec3 normal;
#endif
#ifdef COLOR_0_LOC
layout(location = COLOR_0_LOC) in vec4 color_0;
#endif
layout(location = INST_M_LOC) in mat4 inst_m;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;
uniform DirectionalLight directional_lights[MAX_DIRECTIONAL_LIGHTS];
uniform int n_directional_lights;
uniform vec3 cam_pos;
uniform vec3 ambient_light;

out vec3 frag_color;

const float WRAP = 0.35;
const float SHININESS = 24.0;
const float SPECULAR = 0.06;
const float RIM = 0.12;

void main()
{
    mat4 model = M * inst_m;
    vec4 world = model * vec4(position, 1.0);
    gl_Position = P * V * world;
#ifdef COLOR_0_LOC
    vec3 albedo = color_0.rgb;
#else
    vec3 albedo = vec3(0.8);
#endif
#ifdef NORMAL_LOC
    vec3 n = mat3(model) * normal;
    float length_n = length(n);
    n = length_n > 1e-8 ? n / length_n : vec3(0.0, 0.0, 1.0);
    vec3 to_eye = normalize(cam_pos - world.xyz);
    if (dot(n, to_eye) < 0.0) n = -n;  // both faces of thin parts shade alike
    float sky = 0.5 + 0.5 * n.y;
    vec3 light = ambient_light * mix(vec3(0.75, 0.74, 0.72), vec3(1.05, 1.06, 1.1), sky);
    float highlight = 0.0;
    for (int i = 0; i < n_directional_lights; i++) {
        vec3 to_light = -directional_lights[i].direction;
        vec3 radiance = directional_lights[i].color * directional_lights[i].intensity;
        light += radiance * max((dot(n, to_light) + WRAP) / (1.0 + WRAP), 0.0);
        highlight += directional_lights[i].intensity * pow(max(dot(n, normalize(to_light + to_eye)), 0.0), SHININESS);
    }
    float rim = pow(1.0 - max(dot(n, to_eye), 0.0), 3.0);
    frag_color = clamp(albedo * light + SPECULAR * highlight + RIM * rim, 0.0, 1.0);
#else
    frag_color = albedo;
#endif
}
