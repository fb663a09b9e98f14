//! The GPU computes the camera-relative vertex position with the same bits as
//! the CPU replica `planet_render::camera_relative::camera_relative`, so the
//! precision measured in `numerics.rs` is what the renderer gets: no shader
//! compiler reassociated the TwoSum away. Runs the renderer's WGSL function in
//! a compute shader on whatever adapter wgpu finds (lavapipe in CI); prints a
//! note and passes when no adapter exists (fails under `PLANET_CI=1`).

mod common;

use planet_render::camera_relative::{
    camera_relative, low_part_f16, low_part_f32, split_f32, SplitOffset, WGSL,
};
use wgpu::util::DeviceExt;

/// Deterministic cases: block-relative positions of blocks from 1 m to
/// 10 000 km, eyes from 0 to 100 km from the vertex.
fn cases(n: usize) -> Vec<([f64; 3], [f64; 3])> {
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    (0..n)
        .map(|k| {
            let block = 10f64.powf(k as f64 % 8.0); // 1 m .. 10 000 km
            let dist = 10f64.powf((k / 8) as f64 % 6.0); // 1 m .. 100 km
            let p = [next() * block, next() * block, next() * block];
            let d = [next() * dist, next() * dist, next() * dist];
            (p, [d[0] - p[0], d[1] - p[1], d[2] - p[2]])
        })
        .collect()
}

#[test]
fn gpu_camera_relative_matches_the_cpu_replica_bit_for_bit() {
    let Some(h) = common::headless(4, 4) else {
        return;
    };
    let (device, queue) = (h.renderer.device(), h.renderer.queue());

    let cases = cases(4096);
    let mut input: Vec<f32> = Vec::with_capacity(cases.len() * 16);
    let mut expected: Vec<[f32; 3]> = Vec::with_capacity(cases.len());
    for (p, off) in &cases {
        let (hi, _) = split_f32(*p);
        let lo = low_part_f32(low_part_f16(*p, hi));
        let o = SplitOffset::new(*off);
        for v in [hi, lo, o.hi, o.lo] {
            input.extend_from_slice(&[v[0], v[1], v[2], 0.0]);
        }
        expected.push(camera_relative(hi, lo, o.hi, o.lo));
    }

    let source = format!(
        "{WGSL}\n{}",
        r#"
@group(0) @binding(0) var<storage, read> inp: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> outp: array<vec4<f32>>;
@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let k = id.x;
    if (k >= arrayLength(&outp)) { return; }
    // The w of the first vector is 0.0: its bits are the opaque zero.
    let r = camera_relative(inp[4u * k].xyz, inp[4u * k + 1u].xyz,
                            inp[4u * k + 2u].xyz, inp[4u * k + 3u].xyz,
                            bitcast<u32>(inp[4u * k].w));
    outp[k] = vec4<f32>(r, 0.0);
}
"#
    );
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("camera_relative test"),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("camera_relative test"),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: Default::default(),
        cache: None,
    });
    let inp = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("in"),
        contents: bytemuck::cast_slice(&input),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let out_size = (cases.len() * 16) as u64;
    let outp = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("out"),
        size: out_size,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: out_size,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipeline.get_bind_group_layout(0),
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: inp.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: outp.as_entire_binding(),
            },
        ],
    });
    let mut enc = device.create_command_encoder(&Default::default());
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups((cases.len() as u32).div_ceil(64), 1, 1);
    }
    enc.copy_buffer_to_buffer(&outp, 0, &readback, 0, out_size);
    queue.submit([enc.finish()]);
    let slice = readback.slice(..);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("poll");
    rx.recv().expect("map callback").expect("map");
    let view = slice.get_mapped_range().expect("mapped range");
    let got: Vec<f32> = bytemuck::cast_slice(&view).to_vec();

    let mut mismatches = 0;
    let mut worst_gain = 0.0f64;
    for (k, e) in expected.iter().enumerate() {
        let g = [got[4 * k], got[4 * k + 1], got[4 * k + 2]];
        if g.map(f32::to_bits) != e.map(f32::to_bits) {
            if mismatches < 5 {
                eprintln!("case {k}: GPU {g:?} CPU {e:?} inputs {:?}", cases[k]);
            }
            mismatches += 1;
        }
        // What the TwoSum buys over the plain f32 sum, for the record.
        let (p, off) = cases[k];
        let plain: f64 = (0..3)
            .map(|c| ((p[c] as f32 + off[c] as f32) as f64 - (p[c] + off[c])).abs())
            .fold(0.0, f64::max);
        let ours: f64 = (0..3)
            .map(|c| (e[c] as f64 - (p[c] + off[c])).abs())
            .fold(0.0, f64::max);
        worst_gain = worst_gain.max(plain - ours);
    }
    println!(
        "GPU camera_relative: {} cases, {mismatches} differ from the CPU replica; largest error removed against the plain f32 sum {worst_gain:.3e} m",
        cases.len()
    );
    assert_eq!(mismatches, 0, "the GPU result differs from the CPU replica");
    // The cases include blocks where the plain sum loses metres.
    assert!(worst_gain > 0.01, "{worst_gain}");
}
