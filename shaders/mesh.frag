#version 450 core
in vec3 v_colour;
in vec2 v_uv;
in float v_z;

layout(location = 0) out vec4 o_rgb;
layout(location = 1) out float o_z;

layout(binding = 0) uniform sampler2D u_texture;
uniform bool u_textured;

void main() {
    vec3 c = v_colour;
    if (u_textured) c *= texture(u_texture, v_uv).rgb;
    o_rgb = vec4(c, 1.0);
    o_z = v_z;
}
