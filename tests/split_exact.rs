//! The exact split without Slurm: 2 detectors x 4 tiles of a 64 x 64 simulated sky,
//! with a model whose neighbour effects (`blooming`, `ipc`) make the halo matter, give
//! the bytes of one `persist run`; a too-small halo does not (so the check can fail).

mod common;
mod split_common;

use persist::tile::{self, Placement, Plan, TileOptions};
use split_common::*;

#[test]
fn two_detectors_by_four_tiles_give_the_bytes_of_one_run() {
    let s = sky();
    let reference = reference(&s, "ref");
    let o = common::bin()
        .args(slurm_args(&s, "split", "2x2"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(printed.contains("8 array task(s), halo 1 px"), "{printed}");
    let split = s.root.path().join("split");
    let work = split.join("work");
    let tiles = std::fs::read_to_string(work.join("tiles.sbatch")).unwrap();
    assert!(tiles.contains("#SBATCH --array=0-7"), "{tiles}");
    let submit = std::fs::read_to_string(work.join("submit.sh")).unwrap();
    assert!(submit.contains("--dependency=afterok:"), "{submit}");
    // The jobs one after the other (the scripts' own commands).
    let o = std::process::Command::new("bash")
        .arg(work.join("run_local.sh"))
        .env("SOURCE_DATE_EPOCH", common::SOURCE_DATE_EPOCH)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_same(&reference, &split);
    // The work files are removed after a successful assembly.
    assert!(!work.join("det1").exists() && !work.join("det2").exists());
}

#[test]
fn a_too_small_halo_gives_other_bytes() {
    let s = sky();
    let reference = reference(&s, "ref");
    let model = persist::model::Model::new(persist::model_file::load(&s.model).unwrap()).unwrap();
    assert_eq!(tile::placement(&model), Placement::Frame);
    assert_eq!(tile::halo_px(&model), Some(1));
    let run = |name: &str, placement: Option<Placement>| {
        let dir = s.root.path().join(name);
        let plan = Plan::new(
            &s.input,
            &dir.join("out"),
            &dir.join("ckpt"),
            &dir.join("work"),
            &model,
            "2x2".parse().unwrap(),
            // the processing time the reference recorded (SOURCE_DATE_EPOCH)
            "2026-03-02T00:00:00.000000Z".into(),
            Default::default(),
            false,
        )
        .unwrap();
        for task in 0..plan.tasks() {
            tile::run_tile_with(&plan, &model, task, TileOptions { placement }).unwrap();
        }
        tile::assemble(&plan, &model, false).unwrap();
        dir
    };
    // The library path with the exact placement gives the reference's bytes ...
    assert_same(&reference, &run("exact", None));
    // ... each tile stepped as an array of its own with no halo does not: the tiles'
    // border pixels miss their neighbours' coupling and blooming.
    let crop = run("crop0", Some(Placement::Crop { halo_px: 0 }));
    let (a, b) = (outputs(&reference), outputs(&crop));
    let differing = a.iter().filter(|(k, v)| b.get(*k) != Some(v)).count();
    assert!(
        differing > 0,
        "a halo of 0 gave the same bytes: the check cannot fail"
    );
    assert_ne!(final_checkpoints(&reference), final_checkpoints(&crop));
}

/// The split starts each detector from its newest checkpoint, as `persist run` does:
/// a run over the first 3 exposures, then the split over all 6, gives the bytes of one
/// run over all 6 (the first outputs are already published and left alone).
#[test]
fn a_split_resumes_from_the_newest_checkpoint() {
    let s = sky();
    let reference = reference(&s, "ref");
    let first = s.root.path().join("first");
    std::fs::create_dir_all(&first).unwrap();
    for e in std::fs::read_dir(&s.input).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        if ["_e000000.h5", "_e000001.h5", "_e000002.h5"]
            .iter()
            .any(|x| name.ends_with(x))
        {
            std::fs::copy(&p, first.join(&name)).unwrap();
        }
    }
    let split = s.root.path().join("split");
    let (code, err) = common::run_batch(&first, &split, &["--model", s.model.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(outputs(&split).len(), 6);
    let o = common::bin()
        .args(slurm_args(&s, "split", "2x2"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan = Plan::load(&split.join("work/plan.json")).unwrap();
    let model = plan.model().unwrap();
    for task in 0..plan.tasks() {
        let r = tile::run_tile(&plan, &model, task).unwrap();
        assert_eq!(r.started_from, Some(2));
        assert_eq!(r.exposures.len(), 3);
    }
    let done = tile::assemble(&plan, &model, false).unwrap();
    assert!(done.iter().all(|d| d.written == 3), "{done:?}");
    assert_same(&reference, &split);
}

/// The assembly refuses to publish anything while a tile is missing, naming it.
#[test]
fn the_assembly_names_a_missing_tile_and_publishes_nothing() {
    let s = sky();
    let dir = s.root.path().join("split");
    let o = common::bin()
        .args(slurm_args(&s, "split", "2x2"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan = Plan::load(&dir.join("work/plan.json")).unwrap();
    let model = plan.model().unwrap();
    for task in (0..plan.tasks()).filter(|&t| t != 2) {
        tile::run_tile(&plan, &model, task).unwrap();
    }
    let e = tile::assemble(&plan, &model, false).unwrap_err();
    assert!(
        e.to_string()
            .contains("tile 2 of detector 1 has not finished")
            && e.to_string().contains("state_t002.h5"),
        "{e}"
    );
    assert!(outputs(&dir).is_empty(), "nothing published");
    assert!(common::newest_checkpoint(&dir, 1).is_none());
    // The missing task run, the assembly completes.
    tile::run_tile(&plan, &model, 2).unwrap();
    tile::assemble(&plan, &model, false).unwrap();
    assert_eq!(outputs(&dir).len(), 12);
}

/// Usage errors name what is wrong: a work directory inside the input (its files would
/// be read as products), a task beyond the plan.
#[test]
fn usage_errors_name_the_argument() {
    let s = sky();
    let mut args = slurm_args(&s, "split", "2x2");
    let w = args.iter().position(|a| a == "--work").unwrap();
    args[w + 1] = s.input.join("work").to_string_lossy().into_owned();
    let o = common::bin().args(&args).output().unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("inside the input directory"), "{err}");
    let o = common::bin()
        .args(slurm_args(&s, "split", "2x2"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan = s.root.path().join("split/work/plan.json");
    let o = common::bin()
        .args(["tile", "--plan", plan.to_str().unwrap(), "--task", "8"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("task 8: the plan has 8 tasks"), "{err}");
}
