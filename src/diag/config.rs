//! What `persist diagnose` is asked: the statistic, what chooses and what frees the
//! refits, the residual cells, and their defaults ([`super::diagnose`] module docs say
//! what each does).

use super::eval;
use serde::Serialize;

/// Pixels in the random subsample.
pub const DEFAULT_PIXELS: usize = 2048;

/// Bootstrap replicas.
pub const DEFAULT_BOOTSTRAP: usize = 199;

/// Which residuals the score test uses (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Statistic {
    /// `within` with two illumination events or more, else `pooled` (the output says
    /// which and why).
    Auto,
    Pooled,
    Within,
}

choices!(Statistic, "--statistic", Auto => "auto", Pooled => "pooled", Within => "within");

impl Statistic {
    /// The statistic used on samples from `events` illumination events, and why.
    pub fn resolve(self, events: usize) -> (Statistic, String) {
        match self {
            Statistic::Auto if events >= 2 => (
                Statistic::Within,
                format!(
                    "within (auto: {events} illumination events, compared at equal fluence \
                     and time)"
                ),
            ),
            Statistic::Auto => (
                Statistic::Pooled,
                "pooled (auto: one illumination event, nothing to compare it with; the \
                 within statistic needs two)"
                    .into(),
            ),
            s => (s, format!("{s} (--statistic)")),
        }
    }
}

/// What chooses the candidates that are refitted (module docs, "Decision").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Decide {
    /// The contrasts: untestable classes are not scored; the effects acting on the
    /// covariates the flexible base's residual depends on are refitted.
    #[default]
    Contrast,
    /// The score test alone, as before the contrasts: every library effect is scored
    /// and the [`super::diagnose::REFIT_BY_SCORE`] leading candidates above the bootstrap threshold are
    /// refitted (what the matrix of docs/validation/diagnose_matrix.md measured).
    Score,
}

choices!(Decide, "--decide", Contrast => "contrast", Score => "score");

/// What a candidate's refit frees (module docs, "Refit"). The default, [`Refit::Full`],
/// is that of `persist diagnose` (`--refit`, whose default is this one).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Refit {
    /// The candidate's parameters only; the model's own effects stay as fitted.
    Candidate,
    /// The candidate's parameters and those of the model's own effects, jointly,
    /// against the model's effects refitted alone on the same samples.
    #[default]
    Full,
}

choices!(Refit, "--refit", Candidate => "candidate", Full => "full");

#[derive(Debug, Clone)]
pub struct Config {
    pub pixels: usize,
    pub bootstrap: usize,
    pub seed: u64,
    pub statistic: Statistic,
    /// The residual cells of the refits, the held-out check and the reported RMS
    /// ([`eval::Cells`]; the score test's groups are the statistic's).
    pub cells: eval::Cells,
    /// What every cell compares, in the score test too ([`eval::CellStatistic`]).
    pub cell_statistic: eval::CellStatistic,
    /// How each exposure's background is measured ([`super::data::Background`]).
    pub background: super::data::Background,
    /// What the refits and the held-out check free.
    pub refit: Refit,
    /// Run the joint check when no candidate is significant alone (module docs,
    /// "Joint check"; `persist diagnose --joint`).
    pub joint: bool,
    /// What chooses the candidates refitted (`persist diagnose --decide`).
    pub decide: Decide,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            pixels: DEFAULT_PIXELS,
            bootstrap: DEFAULT_BOOTSTRAP,
            seed: 1,
            statistic: Statistic::Auto,
            cells: eval::Cells::default(),
            cell_statistic: eval::CellStatistic::default(),
            background: super::data::Background::default(),
            refit: Refit::default(),
            joint: false,
            decide: Decide::default(),
        }
    }
}
