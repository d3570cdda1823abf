//! Pixel-grid helpers shared by the model's and the simulator's spatial effects.

/// Call `f(y', x')` for each nearest neighbour of `(y, x)` inside a `ny x nx` array, in
/// the fixed order up, down, left, right. Sums taken through it start from zero and add
/// in that order, so every effect that couples neighbours does the same arithmetic.
#[inline(always)]
pub fn for_each_neighbour(
    ny: usize,
    nx: usize,
    y: usize,
    x: usize,
    mut f: impl FnMut(usize, usize),
) {
    if y > 0 {
        f(y - 1, x);
    }
    if y + 1 < ny {
        f(y + 1, x);
    }
    if x > 0 {
        f(y, x - 1);
    }
    if x + 1 < nx {
        f(y, x + 1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbours_in_order_and_clipped_at_the_edges() {
        let mut v = Vec::new();
        for_each_neighbour(3, 3, 1, 1, |y, x| v.push((y, x)));
        assert_eq!(v, [(0, 1), (2, 1), (1, 0), (1, 2)]);
        v.clear();
        for_each_neighbour(3, 3, 0, 2, |y, x| v.push((y, x)));
        assert_eq!(v, [(1, 2), (0, 1)]);
    }
}
