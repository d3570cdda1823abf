//! `persist run --watch`: notify events plus a periodic rescan feed the [`Stage`].
//!
//! - Events (inotify through `notify`): a rename *to* a final name (`*.h5`, not `.`-led,
//!   not `*.part`) announces a complete product (ICD: upstream writes under a temporary
//!   name and renames); so does a close after writing under the final name. Creation
//!   events are never acted on (the file is still empty then).
//! - Rescan every `poll_interval` with walkdir (file systems without events, e.g. NFS,
//!   and files written in place): a file found only by a scan is read once a second scan
//!   sees the same size and modification time. A cache of (path, size, mtime) keeps a
//!   rescan from re-reading the headers of files already seen.
//! - Hidden directories under the input (`.quarantine`) are ignored.
//! - The loop checks the stop flag at least every 200 ms and between exposures.

use super::run::{Stage, WatchOpts};
use notify::event::{AccessKind, AccessMode, ModifyKind, RenameMode};
use notify::{EventKind, RecursiveMode, Watcher};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::time::{Duration, Instant};

const TICK: Duration = Duration::from_millis(200);

/// The path an event announces as complete, if any.
fn completed(event: &notify::Event) -> Option<&PathBuf> {
    match event.kind {
        EventKind::Modify(ModifyKind::Name(RenameMode::To)) => event.paths.first(),
        EventKind::Modify(ModifyKind::Name(RenameMode::Both)) => event.paths.last(),
        EventKind::Access(AccessKind::Close(AccessMode::Write)) => event.paths.first(),
        _ => None,
    }
}

/// Under `root`, is any component of `path` hidden (`.`-led)?
fn hidden_under(root: &Path, path: &Path) -> bool {
    path.strip_prefix(root).map_or(true, |rel| {
        rel.components()
            .any(|c| c.as_os_str().to_string_lossy().starts_with('.'))
    })
}

pub(crate) fn watch(stage: &mut Stage<'_>, w: &WatchOpts) {
    let input = stage.cfg.input.clone();
    let root = input.canonicalize().unwrap_or_else(|_| input.clone());
    let stop = stage.ops.stop.clone();
    let (tx, rx) = mpsc::channel::<notify::Result<notify::Event>>();
    let watcher = if w.events {
        let made = notify::recommended_watcher(move |res| {
            let _ = tx.send(res);
        })
        .and_then(|mut wt| {
            wt.watch(&input, RecursiveMode::Recursive)?;
            Ok(wt)
        });
        match made {
            Ok(wt) => Some(wt),
            Err(e) => {
                tracing::warn!(error = %e, input = %input.display(),
                    "file system events unavailable: polling only");
                None
            }
        }
    } else {
        None
    };
    tracing::info!(input = %input.display(), events = watcher.is_some(),
        poll_interval_s = w.poll_interval.as_secs_f64(),
        gap_timeout_s = stage.ops.gap_timeout.as_secs_f64(), "watching");
    stage.scan(Instant::now(), true);
    let mut next_scan = Instant::now() + w.poll_interval;
    let mut last_wait_log = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        stage.advance(Instant::now(), false);
        stage.update_metrics(false);
        if stop.load(Ordering::SeqCst) {
            break;
        }
        let wait = next_scan
            .saturating_duration_since(Instant::now())
            .min(TICK);
        let mut events = Vec::new();
        if watcher.is_some() {
            match rx.recv_timeout(wait) {
                Ok(ev) => {
                    events.push(ev);
                    events.extend(rx.try_iter());
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => std::thread::sleep(wait),
            }
        } else {
            std::thread::sleep(wait);
        }
        let now = Instant::now();
        for ev in events {
            match ev {
                Ok(ev) => {
                    if let Some(p) = completed(&ev) {
                        let canon_parent = p
                            .parent()
                            .and_then(|d| d.canonicalize().ok())
                            .map(|d| d.join(p.file_name().unwrap_or_default()));
                        let under = canon_parent.as_deref().unwrap_or(p);
                        if super::queue::is_candidate(p) && !hidden_under(&root, under) {
                            stage.observe_path(p, now);
                        }
                    }
                }
                Err(e) => tracing::warn!(error = %e, "file system event error"),
            }
        }
        if now >= next_scan {
            stage.scan(now, false);
            next_scan = now + w.poll_interval;
        }
        if now.duration_since(last_wait_log) >= Duration::from_secs(60) {
            last_wait_log = now;
            for (det, last, queued) in stage.waiting() {
                if let Some(first) = queued.first() {
                    tracing::info!(detector = det.0, last_processed = ?last,
                        waiting = queued.len(), next_queued = first,
                        "waiting for a missing exposure");
                }
            }
        }
    }
    // The stop may have come while waiting: one more pass writes the tail checkpoint.
    stage.advance(Instant::now(), false);
    tracing::info!("stop requested: exposure in hand finished, checkpoints written");
    drop(watcher);
}
