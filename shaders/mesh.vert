#version 450 core
// Opaque geometry through the pinhole of the intrinsics (OpenCV pixels; image row v is
// framebuffer row v). Writes the camera-frame z for the ray pass.
layout(location = 0) in vec3 a_p_world;
layout(location = 1) in vec3 a_colour;
layout(location = 2) in vec2 a_uv;

uniform mat4 u_camera_from_world;
uniform vec4 u_K;        // fx, fy, cx, cy
uniform vec2 u_size;     // width, height in pixels
uniform vec2 u_near_far; // mm

out vec3 v_colour;
out vec2 v_uv;
out float v_z;

void main() {
    const vec3 p = (u_camera_from_world * vec4(a_p_world, 1.0)).xyz;
    const float n = u_near_far.x, f = u_near_far.y;
    // u = fx x / z + cx; NDC x = 2 (u + 0.5) / W - 1, times w = z.
    gl_Position = vec4(2.0 * (u_K.x * p.x + (u_K.z + 0.5) * p.z) / u_size.x - p.z,
                       2.0 * (u_K.y * p.y + (u_K.w + 0.5) * p.z) / u_size.y - p.z,
                       (p.z * (f + n) - 2.0 * f * n) / (f - n), p.z);
    v_colour = a_colour;
    v_uv = a_uv;
    v_z = p.z;
}
