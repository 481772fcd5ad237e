#version 330 core
// The colour is lit per vertex in mesh.vert; fragments only interpolate it.

in vec3 frag_color;
out vec4 out_color;

void main()
{
    out_color = vec4(frag_color, 1.0);
}
