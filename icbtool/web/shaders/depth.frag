// Shadow-map pass: no colour (the target's colour writes are masked off).
precision highp float;
out vec4 o_color;

void main() {
    o_color = vec4(0.0);
}
