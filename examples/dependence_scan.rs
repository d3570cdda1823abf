//! The first step of `persist diagnose` alone: what the residual depends on
//! (`persist::diag::contrast::dependences`, event-level classes against the pixel
//! reference, pixel-level ones against the flexible base) and the separation of the
//! two leading kinds (`persist::diag::separate`), with `diagnose`'s defaults and
//! against the reference `--reference auto` resolves to; when no contrast names a kind,
//! the decay's shape against the fluence (`persist::diag::shape`). Prints one Markdown table
//! row: the classes that depend (share of the residual explained beyond the
//! permutations' mean, z), the separation, the kind named, and whether it is `EXPECT`
//! (`none`: nothing should be named). For measuring the naming step on many sequences
//! without the refits (scripts/kinds_table.sh).
//!
//! ```sh
//! target/release/examples/dependence_scan LAB_DIR MODEL.json LABEL EXPECT
//! ```
//!
//! With `SCAN_VERBOSE` set, every class's statistic, its permutations and its residual
//! by covariate bin (and, for the neighbours, the pixels next to far brighter ones) go
//! to stderr.
use persist::diag::config::Config;
use persist::diag::contrast::{self, Bases};
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::diag::reference::{self, Reference};
use persist::diag::separate::{self, Told};
use persist::model::effects::REGISTRY;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() != 5 {
        eprintln!("usage: dependence_scan LAB_DIR MODEL.json LABEL EXPECT");
        std::process::exit(2);
    }
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let cfg = Config::default();
    let model = match reference::resolve(Reference::Auto, &model).0 {
        Reference::Measured => reference::describe(&model, &seq, &cfg).expect("description"),
        _ => model,
    };
    let mut s = Samples::random(&seq, cfg.pixels, cfg.seed)
        .with_cells(cfg.cells)
        .with_statistic(cfg.cell_statistic);
    let base = eval::predict(&model, &seq, &s, false).expect("predict");
    let view = persist::diag::base::View::of_model(&model, &seq);
    let response = persist::model::response::Response::new(&model.amplitude_knots);
    persist::diag::base::scale_noise(&seq, &view, &mut s, &base.current, &response);
    let library: Vec<(&str, &str)> = REGISTRY
        .iter()
        .filter(|d| !model.effects.iter().any(|e| e.name == d.name))
        .filter(|d| d.switch().is_some())
        .map(|d| (d.name, d.covariate))
        .collect();
    let contrasts = contrast::testability(&seq, &s, &library);
    let flexible = persist::diag::base::predict(&seq, &view, &s, &base.current);
    let scaled = persist::diag::base::predict_scaled(&seq, &view, &s, &base.current, &response);
    let bases = Bases {
        flexible: &flexible,
        pixel_reference: &scaled.prediction,
    };
    let mut deps = contrast::dependences(&seq, &s, bases, &contrasts, cfg.seed);
    let sep = separate::separate(&seq, &s, &scaled.prediction, &mut deps, cfg.seed);
    if std::env::var_os("SCAN_VERBOSE").is_some() {
        for d in &deps {
            eprintln!(
                "{:<26} r2 {:.4} null mean {:.4} max {:.4} z {:.1} depends {}",
                d.class, d.r2, d.r2_null_mean, d.r2_null_max, d.z, d.depends
            );
            if let Some(x) = &d.sharp {
                eprintln!("    next to far brighter: {x:?}");
            }
            for (label, blocks, mean) in &d.by_bin {
                eprintln!("    {label:<32} blocks {blocks:>6} mean {mean:+.3}");
            }
        }
    }
    let mut depending: Vec<String> = deps
        .iter()
        .filter(|d| d.depends)
        .map(|d| {
            let sharp = d.sharp.filter(|x| x.depends).map_or(String::new(), |x| {
                format!(
                    ", next to far brighter pixels {:+.2} (z {:.0})",
                    x.mean, x.z
                )
            });
            format!(
                "{} {:.2} % (z {:.0}{sharp})",
                d.class,
                100.0 * (d.r2 - d.r2_null_mean),
                d.z
            )
        })
        .collect();
    let largest_quiet = deps
        .iter()
        .filter(|d| !d.depends)
        .map(|d| d.r2 - d.r2_null_mean)
        .fold(f64::NEG_INFINITY, f64::max);
    let separation = sep.as_ref().map_or("-".to_string(), |p| {
        format!(
            "{:?}: {} given {} {:.2} %, {} given {} {:.2} %",
            p.told,
            p.classes[0],
            p.classes[1],
            100.0 * p.first_given_second.excess_r2,
            p.classes[1],
            p.classes[0],
            100.0 * p.second_given_first.excess_r2
        )
    });
    // the kind the verdict names: the named class, or both classes of a pair the data
    // do not tell apart (the verdict gives the separating measurement)
    let lead = separate::leading(&deps, sep.as_ref()).map(|d| d.class.clone());
    let mut named: Vec<String> = match &sep {
        Some(p) if matches!(p.told, Told::Confounded | Told::Both) => p.classes.to_vec(),
        _ => lead.into_iter().collect(),
    };
    // no contrast names a kind: the decay's shape against the fluence (diag::shape)
    let shape = persist::diag::shape::measure(&s, 0);
    if let Some(d) = shape.as_ref().filter(|d| d.depends) {
        depending.push(format!(
            "fluence_x_time: rise {:.2} (z {:.0})",
            d.rise, d.rise_z
        ));
        if named.is_empty() {
            named.push("fluence_x_time".into());
        }
    }
    let expect = a[4].as_str();
    let right = if expect == "none" {
        named.is_empty()
    } else {
        named.first().is_some_and(|c| c == expect)
    };
    let with_other = expect != "none" && named.len() == 2 && named.iter().any(|c| c == expect);
    println!(
        "| {} | {} | {} | {} | {} | {} |",
        a[3],
        if depending.is_empty() {
            "nothing".to_string()
        } else {
            depending.join("; ")
        },
        if largest_quiet.is_finite() {
            format!("{:.2} %", 100.0 * largest_quiet)
        } else {
            "-".into()
        },
        separation,
        if named.is_empty() {
            "nothing".to_string()
        } else {
            named.join(" / ")
        },
        if right {
            "yes"
        } else if with_other {
            "with one other"
        } else {
            "no"
        }
    );
}
