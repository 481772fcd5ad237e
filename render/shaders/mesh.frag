#version 330 core
// Soft stylised shading for the avatar (replaces pyrender's PBR mesh.frag, which is too slow on llvmpipe):
// wrapped Lambert per directional light, a sky/ground hemisphere ambient, a faint Blinn-Phong highlight and
// a view-dependent rim. Vertex colours are the albedo.

struct DirectionalLight {
    vec3 direction;
    vec3 color;
    float intensity;
};

uniform DirectionalLight directional_lights[MAX_DIRECTIONAL_LIGHTS];
uniform int n_directional_lights;
uniform vec3 cam_pos;
uniform vec3 ambient_light;

in vec3 frag_position;
in vec3 frag_normal;
in vec3 frag_albedo;

out vec4 frag_color;

const float WRAP = 0.35;
const float SHININESS = 24.0;
const float SPECULAR = 0.06;
const float RIM = 0.12;

void main()
{
    vec3 n = normalize(frag_normal);
    vec3 to_eye = normalize(cam_pos - frag_position);
    if (dot(n, to_eye) < 0.0) n = -n;  // both faces of thin parts shade alike
    float sky = 0.5 + 0.5 * n.y;
    vec3 light = ambient_light * mix(vec3(0.75, 0.74, 0.72), vec3(1.05, 1.06, 1.1), sky);
    float highlight = 0.0;
    for (int i = 0; i < n_directional_lights; i++) {
        vec3 to_light = -directional_lights[i].direction;
        vec3 radiance = directional_lights[i].color * directional_lights[i].intensity;
        float diffuse = max((dot(n, to_light) + WRAP) / (1.0 + WRAP), 0.0);
        light += radiance * diffuse;
        vec3 half_vector = normalize(to_light + to_eye);
        highlight += directional_lights[i].intensity * pow(max(dot(n, half_vector), 0.0), SHININESS);
    }
    float rim = pow(1.0 - max(dot(n, to_eye), 0.0), 3.0);
    vec3 color = frag_albedo * light + SPECULAR * highlight + RIM * rim;
    frag_color = vec4(clamp(color, 0.0, 1.0), 1.0);
}
