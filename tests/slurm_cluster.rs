//! The split on a real Slurm: a one-node cluster (scripts/slurm_cluster.sh: munged,
//! slurmctld, slurmd in the foreground, private configuration and ports) runs
//! `persist slurm --submit`'s array of 2 detectors x 4 tiles and its `afterok`
//! assembly job on a 64 x 64 simulated sky, and 2 detectors x 2 tiles of the same sky
//! written as SPHEREx-layout FITS; the outputs and final checkpoints must be
//! byte-identical to one `persist run`. The daemons are stopped by their PIDs
//! afterwards, also when the test fails. A machine where the cluster cannot start
//! (no root, no package) fails this test; `PERSIST_SLURM_TEST=skip` skips it, loudly.

mod common;
mod split_common;

use split_common::*;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const DAEMONS: [&str; 3] = ["munged", "slurmctld", "slurmd"];

struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
    pids: Vec<(String, u32)>,
}

fn script(dir: &Path, action: &str) -> std::process::Output {
    Command::new("bash")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/slurm_cluster.sh"))
        .arg(action)
        .env("PERSIST_SLURM_DIR", dir)
        // a private port pair per test process (two test runs on one machine)
        .env(
            "PERSIST_SLURM_PORT",
            (20_000 + 2 * (std::process::id() % 10_000)).to_string(),
        )
        .output()
        .unwrap()
}

fn alive(pid: u32, name: &str) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/comm")).is_ok_and(|c| c.trim() == name)
}

impl Cluster {
    fn start() -> Cluster {
        let dir = std::env::temp_dir().join(format!("persist-slurm-test-{}", std::process::id()));
        let o = script(&dir, "start");
        let err = String::from_utf8_lossy(&o.stderr);
        let pids = DAEMONS
            .iter()
            .filter_map(|d| {
                let p = std::fs::read_to_string(dir.join("pids").join(format!("{d}.pid"))).ok()?;
                Some((d.to_string(), p.trim().parse().ok()?))
            })
            .collect();
        let c = Cluster {
            conf: dir.join("slurm.conf"),
            dir,
            pids,
        };
        assert!(
            o.status.success(),
            "the one-node Slurm cluster did not start (scripts/slurm_cluster.sh start): {err}"
        );
        assert_eq!(c.pids.len(), 3, "PID files of {DAEMONS:?}");
        c
    }

    fn stop(&mut self) {
        if self.pids.is_empty() {
            return;
        }
        let o = script(&self.dir, "stop");
        assert!(
            o.status.success(),
            "stop: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        for (name, pid) in std::mem::take(&mut self.pids) {
            assert!(
                !alive(pid, &name),
                "{name} ({pid}) still running after stop"
            );
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }

    fn scontrol_states(&self, job: &str) -> Vec<String> {
        let o = Command::new("scontrol")
            .args(["show", "job", job])
            .env("SLURM_CONF", &self.conf)
            .output()
            .unwrap();
        String::from_utf8_lossy(&o.stdout)
            .split_whitespace()
            .filter_map(|w| w.strip_prefix("JobState="))
            .map(str::to_string)
            .collect()
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        // On a failed assertion too: never leave the daemons behind.
        if !self.pids.is_empty() {
            let _ = script(&self.dir, "stop");
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// One cluster at a time in this process (they share the PID's directory and ports).
static CLUSTER: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
fn a_slurm_array_of_two_detectors_by_four_tiles_and_its_assembly_give_the_bytes_of_one_run() {
    split_on_a_cluster(sky(), "2x2", 8);
}

#[test]
fn fits_inputs_in_a_slurm_array_of_two_detectors_by_two_tiles_give_the_bytes_of_one_run() {
    split_on_a_cluster(sky_fits(), "1x2", 4);
}

/// `persist slurm --submit` of `s` in `tiles` (`tasks` array tasks in all) on the
/// one-node cluster, against one `persist run`.
fn split_on_a_cluster(s: Sky, tiles: &str, tasks: usize) {
    if std::env::var("PERSIST_SLURM_TEST").as_deref() == Ok("skip") {
        eprintln!("SKIPPED: the Slurm cluster test (PERSIST_SLURM_TEST=skip)");
        return;
    }
    let _one = CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let t0 = Instant::now();
    let reference = reference(&s, "ref");
    let mut cluster = Cluster::start();
    let started = t0.elapsed();
    let o = common::bin()
        .args(slurm_args(&s, "slurm", tiles))
        .arg("--submit")
        .env("SLURM_CONF", &cluster.conf)
        .output()
        .unwrap();
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{printed}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let ids: Vec<&str> = printed
        .lines()
        .find_map(|l| l.strip_prefix("submitted tiles "))
        .map(|l| l.split(" assemble ").collect())
        .unwrap_or_default();
    let [tiles, assemble] = ids[..] else {
        panic!("no job ids printed: {printed}")
    };
    let limit = Instant::now() + Duration::from_secs(60);
    let done = loop {
        let states = cluster.scontrol_states(assemble);
        let last = states.last().cloned().unwrap_or_default();
        if !["PENDING", "RUNNING", "CONFIGURING", "COMPLETING", ""].contains(&last.as_str()) {
            break last;
        }
        assert!(
            Instant::now() < limit,
            "assembly job {assemble} still {last} after 60 s"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    let work = s.root.path().join("slurm/work");
    let logs: String = std::fs::read_dir(work.join("logs"))
        .map(|d| {
            d.filter_map(|e| e.ok())
                .map(|e| {
                    format!(
                        "{}: {}",
                        e.path().display(),
                        std::fs::read_to_string(e.path()).unwrap_or_default()
                    )
                })
                .collect()
        })
        .unwrap_or_default();
    assert_eq!(done, "COMPLETED", "assembly job {assemble}; logs:\n{logs}");
    let tile_states = cluster.scontrol_states(tiles);
    assert_eq!(tile_states.len(), tasks, "{tile_states:?}");
    assert!(
        tile_states.iter().all(|s| s == "COMPLETED"),
        "{tile_states:?}"
    );
    let jobs_done = t0.elapsed();
    assert_same(&reference, &s.root.path().join("slurm"));
    cluster.stop();
    eprintln!(
        "slurm cluster test: cluster idle at {:.1} s, jobs done at {:.1} s, stopped at {:.1} s",
        started.as_secs_f64(),
        jobs_done.as_secs_f64(),
        t0.elapsed().as_secs_f64()
    );
}
