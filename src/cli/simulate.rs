//! `persist simulate lab|sky|family`: the options and the simulation written as it runs.

use super::parse::parse_flag;
use clap::{Args, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Subcommand, Debug)]
pub enum SimScenario {
    /// The paper's laboratory test: a 613 s integration lit for 481 s through a pinhole,
    /// then 180 s dark integrations (the first keeps its ramp).
    Lab(LabArgs),
    /// A SPHEREx-like survey: 112 s integrations, slews, zodiacal light, stars.
    Sky(SkyArgs),
    /// A laboratory sequence from the second, independent truth generator
    /// (`persist::trapgen`: continuous emission-time densities, finite capture, each
    /// seed its own detector), optionally with hidden effects.
    Family(FamilyArgs),
}

#[derive(Args, Debug)]
pub struct FamilyArgs {
    /// Output directory (products; truth in OUT/truth).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Array size N (N x N pixels).
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// `single` (the paper's: one 481 s illumination, then darks) or `campaign` (six
    /// illuminations: durations, a repeat, temperatures; `persist::trapgen`).
    #[arg(long, default_value_t = persist::trapgen::scene::SequenceKind::Single,
          value_parser = parse_flag::<persist::trapgen::scene::SequenceKind>)]
    pub sequence: persist::trapgen::scene::SequenceKind,
    /// Dark integrations after a single illumination (180 s each).
    #[arg(long, default_value_t = persist::trapgen::DEFAULT_DARKS)]
    pub darks: usize,
    /// Leave the right-hand quarter unlit (otherwise every pixel is lit).
    #[arg(long)]
    pub dark_pixels: bool,
    /// Add the grid of one-pixel pinholes: `on`, `off` [default: drawn by the seed].
    #[arg(long)]
    pub pinholes: Option<OnOff>,
    /// A hidden effect CLASS:FORM (repeatable), e.g. `soak:capture`; see
    /// `persist::trapgen` for the forms and their physics.
    #[arg(long = "hidden", value_parser = parse_flag::<persist::trapgen::hidden::Hidden>)]
    pub hidden: Vec<persist::trapgen::hidden::Hidden>,
}

/// `on` or `off`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

#[derive(Args, Debug)]
pub struct LabArgs {
    /// Output directory (products; truth in OUT/truth).
    #[arg(long)]
    pub out: PathBuf,
    /// Array size N (N x N pixels).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Dark integrations after the illumination (default 280 = 14 h; ignored with
    /// --campaign).
    #[arg(long, default_value_t = 280)]
    pub darks: usize,
    /// Chain several illuminations of different durations, fluxes and temperatures
    /// (see `persist::sim::lab` for the default campaign).
    #[arg(long)]
    pub campaign: bool,
    /// Where the campaign's spot is: `centred` (every illumination the same pattern,
    /// scaled), `shifted` (the spot moved for illuminations 2-5, so that radius and
    /// fluence do not go together; `persist::sim::lab`, "Shifted spots") or `pinholes`
    /// (the centred campaign plus a grid of one-pixel pinholes, for effects that couple
    /// neighbours; "Sharp pinholes"), or `paper` (the centred spots with every pixel
    /// lit at 30 e-/s or more, like the paper's laboratory data, so that no pixel stays
    /// below 3000 e-; also without --campaign; "The paper's pattern").
    #[arg(long, default_value_t = persist::sim::lab::Spots::default(),
          value_parser = parse_flag::<persist::sim::lab::Spots>)]
    pub spots: persist::sim::lab::Spots,
    /// With `--spots paper`: keep a corner of size/8 x size/8 pixels unlit, so that the
    /// sequence has pixels that were never lit.
    #[arg(long)]
    pub dark_pixels: bool,
    /// How long the campaign's dark integrations are: `uniform` (180 s) or `varied`
    /// (illumination 2's darks 60 s; its repeat's 540 s, after a reset 12 s after the
    /// shutter, so that the on-board line fit's bias, which grows with the
    /// integration's length and the decay's curvature, differs between two otherwise
    /// equal illuminations; `persist::sim::lab`, "Dark lengths").
    #[arg(long, default_value_t = persist::sim::lab::DarkLengths::default(),
          value_parser = parse_flag::<persist::sim::lab::DarkLengths>, requires = "campaign")]
    pub dark_lengths: persist::sim::lab::DarkLengths,
    /// Where the campaign's temperatures are: `mixed` (illuminations 4 and 5 at 78 and
    /// 82 K, each also of another length or flux) or `apart` (illumination 4 at 80 K
    /// followed by 3 h of darks, and a sixth illumination, 5's twin at 78 K, so that an
    /// effect of the illumination's length and one of the temperature each show on their
    /// own; `persist::sim::lab`, "Temperatures apart").
    #[arg(long, default_value_t = persist::sim::lab::Temperatures::default(),
          value_parser = parse_flag::<persist::sim::lab::Temperatures>, requires = "campaign")]
    pub temperatures: persist::sim::lab::Temperatures,
    /// Add N more 240 s illuminations at 80 K after illumination 3, each followed by
    /// five darks (15 min), so that the traps still hold the last one's charge when the
    /// next begins (an effect that limits what a full pixel can take in, the
    /// simulator's `capacity`, then acts at every repeat; `persist::sim::lab`,
    /// "Repeated illuminations"). At most 20.
    #[arg(long, default_value_t = 0, requires = "campaign",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new()
              .range(0..=persist::sim::lab::MAX_REPEATS as u64))]
    pub repeats: usize,
    /// Whether the campaign tells the illumination's duration from its history:
    /// `mixed` (the campaign the other options make) or `apart` (three illuminations
    /// appended at 80 K, 481 s, 120 s at four times the flux and 481 s, each followed by
    /// 3 h of darks, so that the last two, each after an equally bright one 3 h before,
    /// are two illuminations of equal
    /// fluence and equal history differ in duration; `persist::sim::lab`, "Durations
    /// apart").
    #[arg(long, default_value_t = persist::sim::lab::Durations::default(),
          value_parser = parse_flag::<persist::sim::lab::Durations>, requires = "campaign")]
    pub durations: persist::sim::lab::Durations,
    /// Switch on a truth effect: NAME[:param=value,...] (repeatable). Names: blooming,
    /// capacity, ipc, linefit_bias, populations, short_tau_boost, soak, temperature.
    #[arg(long = "effect")]
    pub effects: Vec<String>,
}

#[derive(Args, Debug)]
pub struct SkyArgs {
    /// Output directory (products; truth in OUT/truth).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 2040)]
    pub size: usize,
    #[arg(long, default_value_t = 6)]
    pub detectors: u8,
    #[arg(long, default_value_t = 1143)]
    pub exposures: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Switch on a truth effect: NAME[:param=value,...] (repeatable).
    #[arg(long = "effect")]
    pub effects: Vec<String>,
    #[command(flatten)]
    pub sky: SkyOptions,
    /// Product format: `h5` (the ICD), or `fits` (SPHEREx's Level-2 layout with
    /// placeholder VARIANCE, ZODI, PSF and WCS-WAVE; docs/fits.md).
    #[arg(long, default_value = "h5", value_parser = ["h5", "fits"])]
    pub format: String,
    /// With --format fits: write detector D's image in MJy/sr, FACTOR e-/s per MJy/sr
    /// (recorded as ESCONV); repeatable.
    #[arg(long = "fits-gain", value_parser = persist::fits::parse_gain)]
    pub fits_gain: Vec<(u8, f64)>,
}

/// Sky and detector parameters of the sky survey (defaults: `persist::sim::sky::SkyConfig`
/// and `persist::sim::detector::DetectorParams`; docs/validation/floor_scan.md scans them).
#[derive(Args, Debug, Clone, Default)]
pub struct SkyOptions {
    /// Stars brighter than magnitude 12 (the saturation magnitude) per 2040 x 2040 array
    /// at high latitude [default 30].
    #[arg(long)]
    pub n12: Option<f64>,
    /// Slope of the cumulative star counts, dex per magnitude [default 0.35].
    #[arg(long)]
    pub count_slope: Option<f64>,
    /// Faintest star drawn, magnitude [default 18].
    #[arg(long)]
    pub m_faint: Option<f64>,
    /// Fraction of the non-deep pointings that are Galactic-plane fields [default 0.1].
    #[arg(long)]
    pub plane_fraction: Option<f64>,
    /// Star density of a Galactic-plane field relative to high latitude [default 30].
    #[arg(long)]
    pub plane_density: Option<f64>,
    /// Cosmic-ray rate, hits per cm^2 per s [default 5].
    #[arg(long)]
    pub cosmic_rate: Option<f64>,
}

impl SkyOptions {
    /// Overwrite the parameters given on the command line.
    pub fn apply(&self, cfg: &mut persist::sim::sky::SkyConfig) {
        let set = |dst: &mut f64, v: Option<f64>| {
            if let Some(v) = v {
                *dst = v;
            }
        };
        set(&mut cfg.n12_per_array, self.n12);
        set(&mut cfg.count_slope, self.count_slope);
        set(&mut cfg.m_faint, self.m_faint);
        set(&mut cfg.plane_fraction, self.plane_fraction);
        set(&mut cfg.plane_density, self.plane_density);
        set(&mut cfg.detector.cosmic_rate_per_cm2_s, self.cosmic_rate);
    }
}

/// `persist simulate lab|sky`: products and truth written as they are simulated.
pub(super) fn simulate(scenario: SimScenario) -> persist::Result<ExitCode> {
    use persist::sim::{effect::EffectSpec, lab, output::Writer, sky};
    let specs = |v: &[String]| -> persist::Result<Vec<EffectSpec>> {
        v.iter().map(|s| s.parse()).collect()
    };
    let (out, n) = match scenario {
        SimScenario::Lab(a) => {
            let paper = a.spots == lab::Spots::Paper;
            if !a.campaign && !matches!(a.spots, lab::Spots::Centred | lab::Spots::Paper) {
                return Err(persist::Error::invalid(
                    "--spots",
                    format!("`{}` needs --campaign", a.spots),
                ));
            }
            if a.dark_pixels && !paper {
                return Err(persist::Error::invalid(
                    "--dark-pixels",
                    "needs --spots paper",
                ));
            }
            let cfg = lab::LabConfig {
                paper_pattern: paper.then_some(lab::PaperPattern {
                    dark_pixels: a.dark_pixels,
                }),
                size: a.size,
                seed: a.seed,
                darks: a.darks,
                campaign: a.campaign.then(|| {
                    lab::CampaignOptions {
                        spots: a.spots,
                        dark_lengths: a.dark_lengths,
                        temperatures: a.temperatures,
                        repeats: a.repeats,
                        durations: a.durations,
                    }
                    .illuminations()
                }),
                effects: specs(&a.effects)?,
                ..lab::LabConfig::default()
            };
            lab::validate(&cfg)?;
            let mut w = Writer::new(&a.out)?;
            let desc = lab::run(&cfg, |e| w.write(&e))?;
            (a.out, w.finish(desc)?)
        }
        SimScenario::Sky(a) => {
            let mut cfg = sky::SkyConfig {
                size: a.size,
                detectors: a.detectors,
                exposures: a.exposures,
                seed: a.seed,
                effects: specs(&a.effects)?,
                ..sky::SkyConfig::default()
            };
            a.sky.apply(&mut cfg);
            sky::validate(&cfg)?;
            let n = sky::write(&cfg, &a.out)?;
            if a.format == "fits" {
                let opts = persist::fits::export::ExportOptions {
                    gains: a.fits_gain.iter().copied().collect(),
                    placeholders: true,
                };
                persist::fits::export::convert_dir(&a.out, &opts)?;
            }
            (a.out, n)
        }
        SimScenario::Family(a) => {
            let cfg = persist::trapgen::FamilyConfig {
                size: a.size,
                seed: a.seed,
                sequence: a.sequence,
                darks: a.darks,
                dark_pixels: a.dark_pixels,
                pinholes: a.pinholes.map(|p| p == OnOff::On),
                hidden: a.hidden,
            };
            persist::trapgen::validate(&cfg)?;
            let mut w = Writer::new(&a.out)?;
            let desc = persist::trapgen::run(&cfg, |e| w.write(&e))?;
            (a.out, w.finish(desc)?)
        }
    };
    out!(
        "persist simulate: {n} products in {}, truth in {}",
        out.display(),
        out.join("truth").display()
    );
    Ok(ExitCode::SUCCESS)
}
