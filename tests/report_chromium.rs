//! The report of `persist compare` opens in headless Chromium with no console message
//! and its plots are visible.
//!
//! How: a 64 x 64 laboratory sequence with a hidden `ipc` (and the same seed without
//! it, as the touched-pixel baseline), compared with two models; Debian's `chromium`
//! takes a screenshot of `report.html` with `--enable-logging=stderr --log-level=0`,
//! which logs every console message of the page as an `INFO:CONSOLE` line on stderr.
//! The report has no script, so *any* console line (an error, an uncaught exception, a
//! blocked resource) fails the test. The PNG is decoded and the plots' pixels counted:
//! the blue of the residual curves (plotters' `BLUE`, drawn only inside the SVG
//! figures) must appear in at least 7 separate horizontal bands (one per breakdown
//! figure), and the heat map's coloured cells must be there.
//!
//! Both checks are shown to be able to fail, in the same test: a copy of the report
//! with a script error must produce an `Uncaught` console line, and a copy with its SVG
//! figures removed must show no plot pixels.
//!
//! Chromium: `apt-get install -y chromium` (CI's `.ci/run` does it). Without it the
//! test fails naming that command, unless `PERSIST_SKIP_CHROMIUM=1`.
//! `PERSIST_SCREENSHOT_OUT=PATH` also copies the screenshot to PATH (how
//! docs/img/report_screenshot.png is made).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const WIDTH: u32 = 1400;
const HEIGHT: u32 = 3600;

mod common;
use common::persist_ok as persist;

fn find_chromium() -> Option<PathBuf> {
    if let Ok(p) = std::env::var("PERSIST_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    for dir in std::env::split_paths(&path) {
        for name in ["chromium", "chromium-browser"] {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// Screenshot `html` into `png`; returns Chromium's stderr.
fn screenshot(chromium: &Path, html: &Path, png: &Path, profile: &Path) -> String {
    let err_path = png.with_extension("stderr.txt");
    let err = std::fs::File::create(&err_path).unwrap();
    let mut child = Command::new(chromium)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--enable-logging=stderr",
            "--log-level=0",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--window-size={WIDTH},{HEIGHT}"))
        .arg(format!("--screenshot={}", png.display()))
        .arg(format!("file://{}", html.display()))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err)
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    loop {
        if let Some(st) = child.try_wait().unwrap() {
            let e = std::fs::read_to_string(&err_path).unwrap_or_default();
            assert!(st.success(), "chromium failed ({st}): {e}");
            return e;
        }
        if t0.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("chromium did not finish in 120 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn console_lines(stderr: &str) -> Vec<&str> {
    stderr.lines().filter(|l| l.contains(":CONSOLE")).collect()
}

struct Pixels {
    width: usize,
    height: usize,
    rgb: Vec<[u8; 3]>,
}

fn decode(path: &Path) -> Pixels {
    let dec = png::Decoder::new(std::fs::File::open(path).unwrap());
    let mut reader = dec.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let ch = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => panic!("unexpected PNG colour type {other:?}"),
    };
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let rgb = buf[..info.buffer_size()]
        .chunks_exact(ch)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    Pixels {
        width: info.width as usize,
        height: info.height as usize,
        rgb,
    }
}

/// (non-white pixels, 100-px bands holding >= 30 curve-blue pixels, heat-map pixels)
fn plot_pixels(p: &Pixels) -> (usize, usize, usize) {
    let is_blue = |c: &[u8; 3]| c[0] < 60 && c[1] < 60 && c[2] > 200;
    // the map's cells: red (255, g=b<235) or blue (r=g<235, 255), not the curves' blue
    let is_cell = |c: &[u8; 3]| {
        (c[0] == 255 && c[1] == c[2] && c[1] < 235)
            || (c[2] == 255 && c[0] == c[1] && c[0] >= 60 && c[0] < 235)
    };
    let non_white = p.rgb.iter().filter(|c| c.iter().any(|v| *v < 245)).count();
    let mut bands = 0;
    for b in 0..p.height.div_ceil(100) {
        let rows = b * 100..((b + 1) * 100).min(p.height);
        let n = rows
            .flat_map(|y| p.rgb[y * p.width..(y + 1) * p.width].iter())
            .filter(|c| is_blue(c))
            .count();
        bands += (n >= 30) as usize;
    }
    let cells = p.rgb.iter().filter(|c| is_cell(c)).count();
    (non_white, bands, cells)
}

#[test]
fn report_opens_in_headless_chromium_without_console_messages_and_shows_its_plots() {
    let Some(chromium) = find_chromium() else {
        if std::env::var("PERSIST_SKIP_CHROMIUM").as_deref() == Ok("1") {
            eprintln!("chromium not found; skipped because PERSIST_SKIP_CHROMIUM=1");
            return;
        }
        panic!(
            "chromium not found on PATH: install it with `apt-get install -y chromium` \
             (CI's .ci/run does), or set PERSIST_SKIP_CHROMIUM=1 to skip this test"
        );
    };
    let tmp = tempfile::tempdir().unwrap();
    let d = |n: &str| tmp.path().join(n).display().to_string();
    for (dir, effect) in [("lab", Some("ipc:alpha=0.02")), ("base", None)] {
        let mut a = vec![
            "simulate", "lab", "--size", "64", "--darks", "40", "--seed", "3", "--out",
        ];
        let out = d(dir);
        a.push(&out);
        if let Some(e) = effect {
            a.extend(["--effect", e]);
        }
        persist(&a);
    }
    let paper = persist(&["model", "default"]);
    std::fs::write(d("paper.json"), &paper).unwrap();
    let mut m: serde_json::Value = serde_json::from_str(&paper).unwrap();
    m["effects"] = serde_json::json!([{"name": "ipc", "params": {"alpha": 0.02}}]);
    std::fs::write(d("ipc.json"), m.to_string()).unwrap();
    persist(&[
        "compare",
        "--input",
        &d("lab"),
        "--model",
        &d("paper.json"),
        "--model",
        &d("ipc.json"),
        "--touched-baseline",
        &d("base"),
        "--report",
        &d("cmp"),
    ]);
    let html = tmp.path().join("cmp/report.html");
    let text = std::fs::read_to_string(&html).unwrap();
    assert!(text.contains("missed @0.1 of touched"));

    let profile = tmp.path().join("profile");
    let shot = tmp.path().join("shot.png");
    let err = screenshot(&chromium, &html, &shot, &profile);
    let console = console_lines(&err);
    assert!(console.is_empty(), "console messages: {console:#?}");
    let px = decode(&shot);
    assert_eq!((px.width, px.height), (WIDTH as usize, HEIGHT as usize));
    let (non_white, bands, cells) = plot_pixels(&px);
    eprintln!(
        "report screenshot: {non_white} non-white pixels of {}, {bands} bands with curves, {cells} heat-map pixels",
        px.rgb.len()
    );
    assert!(
        non_white > px.rgb.len() / 50,
        "page nearly blank: {non_white} non-white pixels"
    );
    assert!(bands >= 7, "curves visible in only {bands} bands");
    assert!(cells >= 500, "heat map not visible: {cells} pixels");
    if let Ok(out) = std::env::var("PERSIST_SCREENSHOT_OUT") {
        std::fs::copy(&shot, out).unwrap();
    }

    // The checks can fail: a script error is seen ...
    let bad = tmp.path().join("cmp/bad.html");
    std::fs::write(
        &bad,
        text.replace("<body>", "<body><script>undefined_fn();</script>"),
    )
    .unwrap();
    let err = screenshot(&chromium, &bad, &tmp.path().join("bad.png"), &profile);
    assert!(
        console_lines(&err).iter().any(|l| l.contains("Uncaught")),
        "the console check missed a script error: {err}"
    );
    // ... and a report without its figures shows no plot pixels.
    let mut bare = String::new();
    let mut rest = text.as_str();
    while let Some(i) = rest.find("<svg") {
        bare += &rest[..i];
        let j = rest[i..].find("</svg>").unwrap() + i + "</svg>".len();
        rest = &rest[j..];
    }
    bare += rest;
    let bare_path = tmp.path().join("cmp/bare.html");
    std::fs::write(&bare_path, bare).unwrap();
    let bare_png = tmp.path().join("bare.png");
    screenshot(&chromium, &bare_path, &bare_png, &profile);
    let (_, bands, cells) = plot_pixels(&decode(&bare_png));
    assert_eq!((bands, cells), (0, 0), "plot pixels without plots");
}
