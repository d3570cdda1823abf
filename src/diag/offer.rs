//! The addition `persist diagnose` offers when it names a kind but no library effect
//! passes the gates against the measurements' description: the refitted candidate
//! (a library effect, or the data-driven term of [`super::data_term`]) that predicts
//! held-out data best against the pixel reference.
//!
//! # Rule
//! Each candidate refitted ([`super::diagnose`], "Identify") and the data-driven term
//! are held out as every candidate is ([`super::refit::held_out`]): fitted, with the
//! model's own effects, on one half of the illumination events (or of the sampled
//! pixels), and judged on the other. The judge here is the pixel reference
//! ([`super::base::predict_scaled`]) fitted on the test half alone, once on the
//! prediction without the candidate and once with it
//! ([`super::refit::HeldOut::pixel_reference`]): what the reference cannot take in by
//! itself (a per-pixel amplitude and decay shape, a response per fluence and a decay
//! per time shared by all illuminations) and the candidate fitted elsewhere predicts.
//! The candidate with the largest pooled gain `1 - RMS_after / RMS_before` is offered
//! when each fold gains and the pooled gain is larger than that of every one of
//! [`super::refit::PERMUTATIONS`] permutations of its predicted change
//! (`super::refit::permuted_change`: the change moved to other pixels and, with
//! several illumination events, to other events), measured on the same halves: the
//! gate is calibrated on the data, a false offer has a chance of at most 1 in 20 when
//! the change carries nothing about where it applies. A gain measured
//! against the pixel reference is not against a misfit of the description: on the
//! second generator's campaigns with nothing hidden the pixel reference's RMS is
//! 0.9-1.2 (docs/validation/reference_rms.md).
//!
//! # Invariants
//! - Offered only when the verdict names a kind and nothing is significant (the
//!   caller's condition); what is offered is one of the candidates or the data term,
//!   named here, whose command the verdict prints.
//! - Nothing here fits: it reads the held-out checks already made.

use super::data_term::DataTerm;
use super::finding::Candidate;
pub use super::finding::Offer;
use super::refit::PixelHeldOut;

/// Whether a held-out check against the pixel reference supports an offer: each fold
/// gains and the pooled gain exceeds that of every permutation of the candidate's
/// predicted change ([`PixelHeldOut::beats_permutations`]).
fn passes(p: &PixelHeldOut) -> bool {
    p.beats_permutations()
}

/// The offer among the refitted candidates of `ranking` and `data_term` (module docs);
/// None when none passes. Ties go to the first in ranking order, the data term last.
pub fn choose(ranking: &[Candidate], data_term: Option<&DataTerm>) -> Option<Offer> {
    let library = ranking.iter().filter_map(|c| {
        let p = c.held_out.as_ref()?.pixel_reference.clone()?;
        Some(Offer {
            effect: c.effect.clone(),
            data_term: false,
            pixel_reference: p,
        })
    });
    let term = data_term.and_then(|t| {
        let p = t.held_out.as_ref()?.pixel_reference.clone()?;
        Some(Offer {
            effect: t.effect.clone(),
            data_term: true,
            pixel_reference: p,
        })
    });
    library
        .chain(term)
        .filter(|o| passes(&o.pixel_reference))
        .fold(None, |best: Option<Offer>, o| match best {
            Some(b) if b.pixel_reference.gain >= o.pixel_reference.gain => Some(b),
            _ => Some(o),
        })
}

#[cfg(test)]
mod tests {
    use super::super::refit::PERMUTATIONS;
    use super::*;

    /// A held-out check whose permutations gained at most 0.02.
    fn gain(g: f64, folds: [f64; 2]) -> PixelHeldOut {
        PixelHeldOut {
            rms_before: 1.0,
            rms_after: 1.0 - g,
            gain: g,
            fold_gains: folds.to_vec(),
            gain_held: g,
            permuted_gains: (0..PERMUTATIONS).map(|k| 0.02 - 0.001 * k as f64).collect(),
        }
    }

    fn candidate(effect: &str, p: Option<PixelHeldOut>) -> Candidate {
        Candidate {
            effect: effect.into(),
            score: 0.0,
            score_rank: 1,
            threshold: 0.0,
            passes_score: false,
            delta_bic: None,
            rms_before: None,
            rms_after: None,
            held_out: p.map(|p| super::super::refit::HeldOut {
                folds: Vec::new(),
                rms_before: 1.0,
                rms_after: 1.0,
                gain: 0.0,
                passes: false,
                moved_cells: 0,
                rms_before_moved: f64::NAN,
                rms_after_moved: f64::NAN,
                gain_moved_cells: f64::NAN,
                pixel_reference: Some(p),
            }),
            significant: false,
            refused_no_field: false,
            covariate: "illumination_time".into(),
            command: String::new(),
            measure_command: None,
            measured_with: None,
        }
    }

    /// The largest gain that passes wins; a gain below a permutation's, one fold that
    /// loses, or permutations not computed, is not offered; nothing held out offers
    /// nothing.
    #[test]
    fn the_best_held_out_gain_against_the_pixel_reference_is_offered() {
        let r = vec![
            candidate("soak", Some(gain(0.10, [0.08, 0.12]))),
            candidate("capacity", Some(gain(0.30, [0.5, -0.01]))),
            candidate("temperature", Some(gain(0.15, [0.1, 0.2]))),
            candidate("blooming", None),
        ];
        let o = choose(&r, None).unwrap();
        assert_eq!(o.effect, "temperature");
        assert!(!o.data_term);
        let weak = vec![candidate("soak", Some(gain(0.015, [0.01, 0.02])))];
        assert_eq!(choose(&weak, None), None);
        let mut unchecked = gain(0.2, [0.2, 0.2]);
        unchecked.permuted_gains.clear();
        assert_eq!(choose(&[candidate("soak", Some(unchecked))], None), None);
        assert_eq!(choose(&[candidate("soak", None)], None), None);
    }
}
