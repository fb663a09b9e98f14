// Composes the planet (an offscreen target) and the text readout onto the
// window surface in one full-screen pass (view/src/app/window/gpu.rs).
@group(0) @binding(0) var scene_tex: texture_2d<f32>;
@group(0) @binding(1) var hud_tex: texture_2d<f32>;

struct VOut { @builtin(position) pos: vec4<f32> };

@vertex fn vs(@builtin(vertex_index) i: u32) -> VOut {
    var out: VOut;
    let x = f32((i << 1u) & 2u);
    let y = f32(i & 2u);
    out.pos = vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
    return out;
}

fn encode(c: vec3<f32>) -> vec3<f32> {
    let lo = c * 12.92;
    let hi = 1.055 * pow(c, vec3<f32>(1.0 / 2.4)) - 0.055;
    return select(hi, lo, c <= vec3<f32>(0.0031308));
}

@fragment fn fs(in: VOut) -> @location(0) vec4<f32> {
    let p = vec2<i32>(in.pos.xy);
    let sd = vec2<i32>(textureDimensions(scene_tex));
    var c = textureLoad(scene_tex, min(p, sd - vec2<i32>(1)), 0).rgb;
    let hd = vec2<i32>(textureDimensions(hud_tex));
    if (p.x < hd.x && p.y < hd.y) {
        let h = textureLoad(hud_tex, p, 0);
        c = mix(c, h.rgb, h.a);
    }
    if (ENCODE) {
        c = encode(c);
    }
    return vec4<f32>(c, 1.0);
}
