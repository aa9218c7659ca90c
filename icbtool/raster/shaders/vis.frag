// Visibility pass of the deferred renderer: which face covers each pixel, nothing else (a
// software rasterizer shades whole 4x4 blocks, so with small triangles most fragment work
// would be wasted; resolve.frag then shades every pixel exactly once).
// Output (GL_R32F, cleared to 0): +-(face index + 1), + for front faces, - for back faces
// (exact in float32 below 2^24 faces). The face comes from a flat attribute of the face's own
// provoking vertex (cheaper than gl_PrimitiveID on llvmpipe).
flat in float v_face;
layout(location = 0) out float o_id;

void main() {
    o_id = gl_FrontFacing ? v_face : -v_face;
}
