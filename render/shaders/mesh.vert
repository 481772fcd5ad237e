#version 330 core
// A light replacement of pyrender's mesh.vert: the model matrices here are rigid, so the normal matrix is
// mat3(M) instead of pyrender's per-vertex transpose(inverse(M)), which dominates vertex cost on llvmpipe.

layout(location = 0) in vec3 position;
layout(location = NORMAL_LOC) in vec3 normal;
#ifdef COLOR_0_LOC
layout(location = COLOR_0_LOC) in vec4 color_0;
#endif
layout(location = INST_M_LOC) in mat4 inst_m;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;

out vec3 frag_position;
out vec3 frag_normal;
out vec3 frag_albedo;

void main()
{
    mat4 model = M * inst_m;
    vec4 world = model * vec4(position, 1.0);
    gl_Position = P * V * world;
    frag_position = world.xyz;
    frag_normal = mat3(model) * normal;
#ifdef COLOR_0_LOC
    frag_albedo = color_0.rgb;
#else
    frag_albedo = vec3(0.8);
#endif
}
