//! Whether two kinds the residual depends on can be told apart in these data.
//!
//! In a campaign the illuminations differ in duration, flux, temperature and history at
//! once, so the base's residual can depend on two event-level covariates
//! ([`super::contrast`]) because it depends on one of them. Each is then tested *given
//! the other*: the same permutation test, with the blocks permuted only among those
//! alike in the other covariate (same fluence bin and the same bin of the other), and
//! the statistic summed over cells split by the other's bins. A covariate that still
//! explains the residual there carries something the other does not.
//!
//! | A given B | B given A | what the data say |
//! |---|---|---|
//! | depends | not | the kind is A (B only follows it) |
//! | not | depends | the kind is B: it is named first |
//! | not | not | confounded: no pair of illuminations differs in one and not the other |
//! | depends | depends | both: each explains what the other does not |
//!
//! "Depends" given the other is the marginal test's rule for an event-level class
//! ([`super::contrast`]): above every permutation (p < 0.01) and explaining at least
//! [`MIN_R2_EVENT`] of the pixel reference's residual beyond the permutations' mean.
//! Both tests use one residual, the pixel reference's, so their effect sizes compare.
//! With many pixel-events a covariate that follows the residual at all is above every
//! permutation, given the other or not, so the effect size decides: on the second
//! generator's campaign with hidden `soak:capture` (64 x 64, seed 2) history given the
//! duration explained 0.74 % and the duration given history 0.54 %, each above every
//! permutation. When
//! two covariates split the events alike, no stratum of one holds two values of the
//! other, the permutations change nothing, and neither depends given the other.
//!
//! # Invariants
//! - Only the two leading event-level classes above every permutation are compared,
//!   and only when the first of them depends (a class above its permutations whose
//!   excess is below [`MIN_R2_EVENT`] is refitted all the same,
//!   [`Dependence::refits`], and may be the kind the other stands in for); the order of
//!   [`super::contrast::dependences`] changes only by moving the second one first when
//!   the data name it and not the first.
//! - Deterministic for a seed: the permutations use the stream of the marginal test.

use super::contrast::{
    base_residual, block_sums, blocks, covariate_bins, explained, null_summary, permutation_null,
    pixel_level, CellSums, Dependence, MIN_R2_EVENT,
};
use super::data::Sequence;
use super::eval::Samples;
use serde::Serialize;
use std::collections::BTreeMap;

/// One class's dependence given another's covariate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Given {
    /// The share of the residual's sum of squares the class explains beyond the
    /// permutations' mean, inside the other's bins.
    pub excess_r2: f64,
    /// `(T - mean) / sd` of the permutations (0 when they all agree).
    pub z: f64,
    /// Above every permutation (p < 0.01) and explaining at least
    /// [`MIN_R2_EVENT`] beyond the permutations' mean: the marginal test's rule for an
    /// event-level class.
    pub depends: bool,
    /// Above every permutation, whatever the effect size.
    pub above_permutations: bool,
    /// Blocks in strata where the class takes two values or more: what the test has.
    pub blocks_with_contrast: usize,
}

/// What the data say of two kinds (module docs' table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Told {
    First,
    Second,
    Confounded,
    Both,
}

/// The two leading event-level classes that depend, each tested given the other.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Separation {
    /// In the marginal test's order.
    pub classes: [String; 2],
    pub first_given_second: Given,
    pub second_given_first: Given,
    pub told: Told,
}

impl Separation {
    /// The class the data name, if they name one.
    pub fn named(&self) -> Option<&str> {
        match self.told {
            Told::First => Some(&self.classes[0]),
            Told::Second => Some(&self.classes[1]),
            Told::Confounded | Told::Both => None,
        }
    }
}

/// The kind the residual depends on, to be named: the class the separation names, else
/// the first that depends.
pub fn leading<'a>(deps: &'a [Dependence], sep: Option<&Separation>) -> Option<&'a Dependence> {
    match sep.and_then(Separation::named) {
        Some(named) => deps.iter().find(|d| d.class == named),
        None => deps.iter().find(|d| d.depends),
    }
}

/// The separation of the two leading event-level classes of `deps` whose `T` is above
/// every permutation, the first of them depending (module docs), and `deps` with the
/// second moved first when only it depends given the other. `None` without such a
/// pair.
pub fn separate(
    seq: &Sequence,
    s: &Samples,
    pixel_reference: &[f64],
    deps: &mut [Dependence],
    seed: u64,
) -> Option<Separation> {
    let lead: Vec<usize> = (0..deps.len())
        .filter(|&i| deps[i].refits() && !pixel_level(&deps[i].class))
        .take(2)
        .collect();
    let [i, j] = lead[..] else {
        return None;
    };
    if !deps[i].depends {
        return None;
    }
    let bl = blocks(s);
    let e = base_residual(s, pixel_reference, false);
    let xa = covariate_bins(seq, s, &deps[i].class, &bl);
    let xb = covariate_bins(seq, s, &deps[j].class, &bl);
    let first_given_second = given(s, &e, &bl, &xa, &xb, seed);
    let second_given_first = given(s, &e, &bl, &xb, &xa, seed);
    let told = match (first_given_second.depends, second_given_first.depends) {
        (true, false) => Told::First,
        (false, true) => Told::Second,
        (false, false) => Told::Confounded,
        (true, true) => Told::Both,
    };
    let out = Separation {
        classes: [deps[i].class.clone(), deps[j].class.clone()],
        first_given_second,
        second_given_first,
        told,
    };
    if told == Told::Second {
        deps[i..=j].rotate_right(1);
    }
    Some(out)
}

/// The dependence on `x` given `cond` (module docs): the blocks with a bin in both.
fn given(
    s: &Samples,
    e: &[f64],
    blocks: &[(usize, usize, i64)],
    x: &[Option<i64>],
    cond: &[Option<i64>],
    seed: u64,
) -> Given {
    let x: Vec<Option<i64>> = x
        .iter()
        .zip(cond)
        .map(|(a, c)| a.filter(|_| c.is_some()))
        .collect();
    let (per_block, ss) = block_sums(s, e, &x, blocks, false);
    given_sums(&per_block, ss, blocks, &x, cond, seed)
}

/// [`given`] on the residual summed per block and cell ([`block_sums`]), `ss` its sum
/// of squares; `x` has no bin where `cond` has none.
fn given_sums(
    per_block: &[CellSums],
    ss: f64,
    blocks: &[(usize, usize, i64)],
    x: &[Option<i64>],
    cond: &[Option<i64>],
    seed: u64,
) -> Given {
    let stat = |xs: &[Option<i64>]| explained(per_block, xs, Some(cond));
    let t = stat(x);
    let null = permutation_null(x, blocks, false, Some(cond), seed, stat);
    let (mean, sd, max) = null_summary(&null);
    let ss = ss.max(1e-12);
    // relative tolerance: permutations that change nothing give `t` again, up to rounding
    let above = t > max + 1e-9 * t.abs();
    Given {
        excess_r2: (t - mean) / ss,
        z: if sd > 1e-9 * t.abs() {
            (t - mean) / sd
        } else {
            0.0
        },
        depends: above && (t - mean) / ss >= MIN_R2_EVENT,
        above_permutations: above,
        blocks_with_contrast: with_contrast(blocks, x, cond),
    }
}

/// Blocks in strata (fluence bin x bin of `cond`) where `x` takes two values or more.
fn with_contrast(blocks: &[(usize, usize, i64)], x: &[Option<i64>], cond: &[Option<i64>]) -> usize {
    let mut strata: BTreeMap<(i64, i64), (Vec<i64>, usize)> = BTreeMap::new();
    for (b, &(_, _, f)) in blocks.iter().enumerate() {
        if let (Some(xb), Some(cb)) = (x[b], cond[b]) {
            let q = strata.entry((f, cb)).or_default();
            if !q.0.contains(&xb) {
                q.0.push(xb);
            }
            q.1 += 1;
        }
    }
    strata
        .values()
        .filter(|(values, _)| values.len() >= 2)
        .map(|(_, n)| n)
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 400 pixel-events of one fluence bin and one cell, residual +-1 by `a`'s bin
    /// (with a small deterministic spread); `b` is independent of `a` or equal to it.
    fn case(b_equals_a: bool) -> (Given, Given) {
        let n = 400;
        let blocks: Vec<(usize, usize, i64)> = (0..n).map(|i| (i % 7, i, 0)).collect();
        let a: Vec<Option<i64>> = (0..n).map(|i| Some((i % 2) as i64)).collect();
        let b: Vec<Option<i64>> = if b_equals_a {
            a.clone()
        } else {
            (0..n).map(|i| Some(((i / 2) % 2) as i64)).collect()
        };
        let r = |i: usize| {
            (if i % 2 == 1 { 1.0 } else { -1.0 }) + 0.3 * (((i * 37) % 11) as f64 / 10.0 - 0.5)
        };
        let per_block: Vec<CellSums> = (0..n).map(|i| vec![(0, r(i), 1.0)]).collect();
        let ss: f64 = (0..n).map(|i| r(i) * r(i)).sum();
        (
            given_sums(&per_block, ss, &blocks, &a, &b, 1),
            given_sums(&per_block, ss, &blocks, &b, &a, 1),
        )
    }

    /// The residual follows `a`: among events alike in `b`, `a` still explains it; among
    /// events alike in `a`, `b` explains nothing.
    #[test]
    fn the_covariate_the_residual_follows_is_the_one_that_depends_given_the_other() {
        let (a_given_b, b_given_a) = case(false);
        assert!(a_given_b.depends, "{a_given_b:?}");
        assert!(a_given_b.excess_r2 > 0.5, "{a_given_b:?}");
        assert!(!b_given_a.depends, "{b_given_a:?}");
        assert_eq!(a_given_b.blocks_with_contrast, 400);
    }

    /// Two covariates that split the events alike: no stratum of one holds two values
    /// of the other, and neither depends given the other.
    #[test]
    fn covariates_that_split_the_events_alike_are_confounded() {
        let (a_given_b, b_given_a) = case(true);
        assert!(!a_given_b.depends && !b_given_a.depends);
        assert_eq!(a_given_b.blocks_with_contrast, 0);
        assert_eq!(a_given_b.z, 0.0);
    }

    #[test]
    fn the_named_class_follows_what_was_told() {
        let g = Given {
            excess_r2: 0.0,
            z: 0.0,
            depends: false,
            above_permutations: false,
            blocks_with_contrast: 0,
        };
        let mut s = Separation {
            classes: ["illumination_time".into(), "earlier_illuminations".into()],
            first_given_second: g,
            second_given_first: g,
            told: Told::Second,
        };
        assert_eq!(s.named(), Some("earlier_illuminations"));
        s.told = Told::Confounded;
        assert_eq!(s.named(), None);
    }
}
