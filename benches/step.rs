//! Criterion micro-benchmark of the model step alone (fused and reference) on a
//! 256 x 256 exposure, six terms. The README's numbers come from `persist bench`
//! (child processes, the memory and I/O bounds, peak memory); this one is for quick
//! comparisons while working on the kernel: `cargo bench --bench step`.

use criterion::{criterion_group, criterion_main, Criterion};
use ndarray::Array2;
use persist::bench::synthetic_frame;
use persist::model::{reference, Input, Model, ModelParams, Output};

fn step(c: &mut Criterion) {
    let n = 256;
    let model = Model::new(ModelParams::default()).unwrap();
    let (image, flags0) = synthetic_frame(n, 1);
    let mut current = Array2::<f32>::zeros((n, n));
    let mut pflags = Array2::<u8>::zeros((n, n));
    for (name, fused) in [("fused step 256^2", true), ("reference step 256^2", false)] {
        let mut state = model.new_state(n, n);
        let mut k = 0u64;
        c.bench_function(name, |b| {
            b.iter(|| {
                let mut flags = flags0.clone();
                let input = Input {
                    image_e_per_s: image.view(),
                    exposure_index: k,
                    t_start_unix_s: 1.77e9 + k as f64 * 150.0,
                    t_exposure_s: 112.0,
                    t_illuminated_s: 112.0,
                    history_incomplete: false,
                    background_e_per_s: None,
                };
                k += 1;
                let mut out = Output {
                    flags: &mut flags,
                    current_e_per_s: &mut current,
                    pflags: &mut pflags,
                };
                if fused {
                    model.step(&mut state, &input, &mut out).unwrap()
                } else {
                    reference::step(&model, &mut state, &input, &mut out).unwrap()
                }
            })
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = step
}
criterion_main!(benches);
