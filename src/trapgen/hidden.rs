//! Hidden effects: each class in two physically distinct forms (`CLASS:FORM`).
//!
//! The physics of each form is in the module docs of [`crate::trapgen`] ("Hidden
//! effects"); this file only names them. Parameters are fixed per form (documented
//! there); what varies from seed to seed is the detector underneath ("Nuisance
//! physics").

use crate::error::{Error, Result};
use std::fmt;
use std::str::FromStr;

/// One hidden effect: a class and one of its forms.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Hidden {
    /// Slow traps capture slowly: a short illumination fills them less.
    SoakCapture,
    /// A deep population fills as sqrt(time) (diffusion), reached only after long
    /// illuminations.
    SoakDiffusion,
    /// A hard per-pixel ceiling on the total trapped charge.
    CapacityCeiling,
    /// Langmuir blocking: sites still occupied by earlier charge are not available.
    CapacityLangmuir,
    /// Arrhenius emission rates.
    TemperatureArrhenius,
    /// The slow population's site density depends on the temperature at filling.
    TemperatureWeight,
    /// Charge above full well spills to the four neighbours through the trap-rich
    /// surface.
    BloomingSpill,
    /// A saturated pixel's field exposes its eight neighbours' traps (no signal moves).
    BloomingField,
    /// Capacitive coupling of the read signal, four neighbours, isotropic.
    IpcCross4,
    /// Capacitive coupling, eight neighbours, anisotropic.
    IpcAniso8,
    /// A smooth map of trap density over the array.
    PopulationsSmooth,
    /// Clustered patches of high trap density.
    PopulationsPatches,
    /// Higher exposure reaches deeper (slower) states of the power-law population.
    ShapeFillDepth,
    /// The fast population has few sites and fills up at low exposure.
    ShapeFastCeiling,
}

/// Every form, in the order of the docs.
pub const ALL: [Hidden; 14] = [
    Hidden::SoakCapture,
    Hidden::SoakDiffusion,
    Hidden::CapacityCeiling,
    Hidden::CapacityLangmuir,
    Hidden::TemperatureArrhenius,
    Hidden::TemperatureWeight,
    Hidden::BloomingSpill,
    Hidden::BloomingField,
    Hidden::IpcCross4,
    Hidden::IpcAniso8,
    Hidden::PopulationsSmooth,
    Hidden::PopulationsPatches,
    Hidden::ShapeFillDepth,
    Hidden::ShapeFastCeiling,
];

/// Forms held aside for the final proof: not run by the matrix unless asked
/// (`--held-out`), and not to be looked at while developing diagnostics.
pub const HELD_ASIDE: [Hidden; 3] = [
    Hidden::TemperatureWeight,
    Hidden::PopulationsPatches,
    Hidden::ShapeFastCeiling,
];

/// Seeds from this one on are held aside for the final proof.
pub const HELD_ASIDE_FIRST_SEED: u64 = 100;

impl Hidden {
    /// The class, as `persist diagnose` names the library effect that stands for it
    /// (`shape` is the fluence-dependent decay shape).
    pub fn class(self) -> &'static str {
        use Hidden::*;
        match self {
            SoakCapture | SoakDiffusion => "soak",
            CapacityCeiling | CapacityLangmuir => "capacity",
            TemperatureArrhenius | TemperatureWeight => "temperature",
            BloomingSpill | BloomingField => "blooming",
            IpcCross4 | IpcAniso8 => "ipc",
            PopulationsSmooth | PopulationsPatches => "populations",
            ShapeFillDepth | ShapeFastCeiling => "shape",
        }
    }

    pub fn form(self) -> &'static str {
        use Hidden::*;
        match self {
            SoakCapture => "capture",
            SoakDiffusion => "diffusion",
            CapacityCeiling => "ceiling",
            CapacityLangmuir => "langmuir",
            TemperatureArrhenius => "arrhenius",
            TemperatureWeight => "weight",
            BloomingSpill => "spill",
            BloomingField => "field",
            IpcCross4 => "cross4",
            IpcAniso8 => "aniso8",
            PopulationsSmooth => "smooth",
            PopulationsPatches => "patches",
            ShapeFillDepth => "fill_depth",
            ShapeFastCeiling => "fast_ceiling",
        }
    }

    pub fn held_aside(self) -> bool {
        HELD_ASIDE.contains(&self)
    }
}

impl fmt::Display for Hidden {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.class(), self.form())
    }
}

impl FromStr for Hidden {
    type Err = Error;
    fn from_str(s: &str) -> Result<Hidden> {
        ALL.iter()
            .copied()
            .find(|h| h.to_string() == s.trim())
            .ok_or_else(|| {
                Error::invalid(
                    "--hidden",
                    format!(
                        "`{s}` is not CLASS:FORM; known: {}",
                        ALL.iter()
                            .map(|h| h.to_string())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                )
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_every_class_has_two_forms() {
        for h in ALL {
            assert_eq!(h.to_string().parse::<Hidden>().unwrap(), h);
            assert_eq!(ALL.iter().filter(|o| o.class() == h.class()).count(), 2);
        }
        assert!("soak:nothing".parse::<Hidden>().is_err());
    }
}
