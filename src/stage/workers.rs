//! `persist run` over several detectors as one worker process per detector.
//!
//! HDF5 serialises every call of a process behind one global lock, so detectors on
//! threads of one process wait for each other's I/O; as separate processes they do not.
//! The parent (which holds the directory lock, `.persist.lock`) starts
//! `persist run ... --worker D` for each detector found in the input, in detector order;
//! each worker processes that detector only, prints its rows of the summary table on its
//! standard output (collected, printed by the parent in detector order) and its logs on
//! its standard error (inherited: forwarded as they come). The parent's exit status is 1
//! when any worker's is not 0. SIGINT/SIGTERM to the parent are forwarded to the
//! workers (each finishes its exposure in hand and writes its checkpoint); when the
//! parent dies, however it dies, the kernel kills its workers (`PR_SET_PDEATHSIG`), so a
//! killed run is one crash, as of a single process, and no worker outlives the lock.
//!
//! The worker of the lowest detector also refuses the products whose detector cannot be
//! read (exactly one worker quarantines them).

use crate::error::{Error, ErrorKind, Result};
use crate::stage::queue;
use crate::units::DetectorId;
use std::collections::BTreeSet;
use std::ffi::OsString;
use std::io::Read;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// The detectors of the products under `input` whose header can be read (through the
/// reader guard when there is one: a file that crashes its reader has no detector).
pub fn detectors(
    input: &Path,
    fits: &crate::product::fits::FitsConfig,
    guard: Option<&crate::guard::Guard>,
) -> Result<BTreeSet<DetectorId>> {
    Ok(queue::candidates(input)?
        .iter()
        .filter_map(|p| crate::guard::read_input_sequence(guard, p, fits).ok())
        .map(|(m, _)| m.detector)
        .collect())
}

/// In a worker, once its SIGINT/SIGTERM handlers are installed: unblock the two signals
/// (blocked from its start by [`run_workers`]), so that a stop the parent forwarded
/// early is delivered now, to the handlers.
pub fn unblock_stop_signals() {
    // SAFETY: plain libc calls on a local signal set.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGINT);
        libc::sigaddset(&mut set, libc::SIGTERM);
        libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut());
    }
}

/// What one worker did.
#[derive(Debug)]
pub struct WorkerOutcome {
    pub detector: DetectorId,
    pub status: ExitStatus,
    /// Its standard output (its rows of the summary table).
    pub stdout: String,
}

/// Run `exe ARGS --worker D [--worker-unattributed]` for every detector, all at once,
/// and wait for them; `stop` (set by a signal) is forwarded as SIGTERM.
pub fn run_workers(
    exe: &Path,
    args: &[OsString],
    detectors: &BTreeSet<DetectorId>,
    stop: &AtomicBool,
) -> Result<Vec<WorkerOutcome>> {
    let mut running: Vec<(DetectorId, Child, std::thread::JoinHandle<String>)> = Vec::new();
    for (k, d) in detectors.iter().enumerate() {
        let mut cmd = Command::new(exe);
        cmd.args(args)
            .arg("--worker")
            .arg(d.0.to_string())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        if k == 0 {
            cmd.arg("--worker-unattributed");
        }
        {
            use std::os::unix::process::CommandExt;
            // SAFETY: prctl, getppid, _exit, sigemptyset, sigaddset and sigprocmask are
            // async-signal-safe and touch no memory of the parent.
            unsafe {
                cmd.pre_exec(|| {
                    if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                    // The parent may have died before the prctl.
                    if libc::getppid() == 1 {
                        libc::_exit(137);
                    }
                    // A stop forwarded before the worker's handlers are installed waits
                    // for them ([`unblock_stop_signals`]) instead of killing it.
                    let mut set: libc::sigset_t = std::mem::zeroed();
                    libc::sigemptyset(&mut set);
                    libc::sigaddset(&mut set, libc::SIGINT);
                    libc::sigaddset(&mut set, libc::SIGTERM);
                    libc::sigprocmask(libc::SIG_BLOCK, &set, std::ptr::null_mut());
                    Ok(())
                });
            }
        }
        let mut child = match cmd.spawn() {
            Ok(c) => c,
            Err(e) => {
                for (_, c, _) in &mut running {
                    let _ = c.kill();
                    let _ = c.wait();
                }
                return Err(Error::new(
                    ErrorKind::Io,
                    format!("cannot start the worker of detector {}: {e}", d.0),
                )
                .path(exe));
            }
        };
        let mut out = child.stdout.take();
        let reader = std::thread::spawn(move || {
            let mut s = String::new();
            if let Some(o) = out.as_mut() {
                let _ = o.read_to_string(&mut s);
            }
            s
        });
        running.push((*d, child, reader));
    }
    let mut forwarded = false;
    let mut statuses: Vec<Option<ExitStatus>> = vec![None; running.len()];
    while statuses.iter().any(Option::is_none) {
        if stop.load(Ordering::SeqCst) && !forwarded {
            forwarded = true;
            for (k, (_, c, _)) in running.iter().enumerate() {
                if statuses[k].is_none() {
                    if let Ok(pid) = i32::try_from(c.id()) {
                        // SAFETY: kill(2) on our own child's pid.
                        unsafe {
                            libc::kill(pid, libc::SIGTERM);
                        }
                    }
                }
            }
        }
        for (k, (_, c, _)) in running.iter_mut().enumerate() {
            if statuses[k].is_none() {
                statuses[k] = c
                    .try_wait()
                    .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(running
        .into_iter()
        .zip(statuses)
        .map(|((detector, _, reader), status)| WorkerOutcome {
            detector,
            status: status.unwrap_or_default(),
            stdout: reader.join().unwrap_or_default(),
        })
        .collect())
}
