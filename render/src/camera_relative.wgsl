// Camera-relative position with one rounding (render/src/camera_relative.rs):
// TwoSum of the high parts, then the low parts and the TwoSum error, then the
// one rounding that matters. Keep in step with `camera_relative()` in Rust.
//
// `zero` must be 0 at run time but unknown to the compiler (a uniform's bits):
// shader compilers treat float arithmetic as reassociable unless told
// otherwise (Mesa's NIR folds `(a + b) - a` to `b`, which zeroes the TwoSum
// error; WGSL has no `precise`), and an OR with an opaque integer is a
// barrier no float rule can see through.
fn opaque3(x: vec3<f32>, zero: u32) -> vec3<f32> {
    return bitcast<vec3<f32>>(bitcast<vec3<u32>>(x) | vec3<u32>(zero));
}

fn camera_relative(
    pos_hi: vec3<f32>,
    pos_lo: vec3<f32>,
    off_hi: vec3<f32>,
    off_lo: vec3<f32>,
    zero: u32,
) -> vec3<f32> {
    let s = opaque3(pos_hi + off_hi, zero);
    let bb = opaque3(s - pos_hi, zero);
    let err = opaque3((pos_hi - (s - bb)) + (off_hi - bb), zero);
    return s + (err + (pos_lo + off_lo));
}
