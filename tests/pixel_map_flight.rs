//! The per-pixel map learned in flight (`persist::pixmap::flight`): built from a
//! simulated sky run (the default model's predictions and flags, `verify`'s tracks), it is
//! written in the laboratory map's format, read back by the stage's model loader, and it
//! tells the simulator's trap populations apart: the pixels it measured have a higher
//! mean ratio in the high population than in the low one (the simulator's truth,
//! `persist::sim::traps::draw_pixels`).

use ndarray::Array2;
use persist::model::{Model, ModelParams};
use persist::pixmap::flight::FlightLearner;
use persist::pixmap::{file, step_exposure, MapConfig};
use persist::verify::track::{Frame, TrackParams, Tracker};

#[test]
fn a_flight_map_from_a_sky_run_is_read_by_the_stage_and_follows_the_true_populations() {
    let size = 64;
    let seed = 5;
    let cfg = persist::sim::sky::SkyConfig {
        size,
        detectors: 1,
        exposures: 1143,
        seed,
        // a crowded sky: more events per pixel in two days
        plane_fraction: 0.5,
        ..Default::default()
    };
    let params = ModelParams::default();
    let model = Model::new(params.clone()).unwrap();
    let mut state = model.new_state(size, size);
    let mut follow = Tracker::new(TrackParams::default(), size, size);
    let map_cfg = MapConfig::default();
    let mut learner = FlightLearner::new(size, size, &map_cfg);
    let mut cur = Array2::<f32>::zeros((size, size));
    let mut pf = Array2::<u8>::zeros((size, size));
    persist::sim::sky::run(&cfg, |s| {
        let e = &s.exposure;
        step_exposure(&model, &mut state, e, None, &mut cur, &mut pf)?;
        let frame = Frame::of(e, cur.view(), pf.view(), None);
        for sample in follow.observe(&frame) {
            learner.add(&sample);
        }
        Ok(())
    })
    .unwrap();
    let map = learner
        .build(1, &params, &map_cfg, None, "flight: test sky")
        .unwrap();
    assert!(map.range_measured[1] && !map.range_measured[0]);
    let [_, seen] = file::observed(&map);
    assert!(seen >= 100, "{seen} pixels measured in flight");

    // written and read back as the stage reads it
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("det1.h5");
    file::write(&path, &map).unwrap();
    let back = file::read(&path).unwrap();
    assert_eq!(back.ratio, map.ratio);
    assert_eq!(back.source, "flight: test sky");
    let named = file::name_maps(params, &[(1, "det1.h5".into(), path.clone())], 1.0).unwrap();
    let model_path = dir.path().join("model.json");
    std::fs::write(&model_path, named.to_json_pretty()).unwrap();
    let loaded = persist::model_file::load(&model_path).unwrap();
    file::attach(&model_path, loaded).unwrap();

    // the measured pixels' ratios follow the true populations
    let lab = persist::sim::lab::LabConfig::default();
    let truth = persist::sim::traps::draw_pixels(&lab.traps, &lab.detector, size, size, seed, 1);
    let names: Vec<&str> = lab
        .traps
        .populations
        .iter()
        .map(|p| p.name.as_str())
        .collect();
    let mean_of = |name: &str| {
        let k = names.iter().position(|n| *n == name).unwrap() as u8;
        let v: Vec<f64> = truth
            .population
            .indexed_iter()
            .filter(|((y, x), q)| **q == k && map.n_obs[[1, *y, *x]] > 0)
            .map(|((y, x), _)| f64::from(map.ratio[[1, y, x]]))
            .collect();
        (v.iter().sum::<f64>() / v.len().max(1) as f64, v.len())
    };
    let (low, n_low) = mean_of("low");
    let (high, n_high) = mean_of("high");
    assert!(n_low >= 10 && n_high >= 10, "{n_low} {n_high}");
    assert!(high > 1.5 * low, "high {high} vs low {low}");
}
