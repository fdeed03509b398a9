//! Row interlacing: the map between physical rows and logical rows.
//!
//! Logical row order lists the physical rows `y` with `y % g == 0` first (ascending),
//! then those with `y % g == 1`, and so on, where `g` is the number of groups (the
//! number of ranks). A contiguous logical span of about `N/g` pixels then covers rows
//! spread over the whole image, which balances the active pixels between ranks. With
//! `g = 1` (interlacing off) the map is the identity.

/// The row permutation for a `width × height` image and `groups` interlace groups.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Interlace {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in rows.
    pub height: u32,
    /// Number of interlace groups; 1 means no interlacing.
    pub groups: u32,
}

impl Interlace {
    /// The interlacing for `groups` groups (usually the number of ranks), or the
    /// identity when `enabled` is false. `groups == 0` is treated as 1.
    pub fn new(width: u32, height: u32, groups: u32, enabled: bool) -> Interlace {
        Interlace {
            width,
            height,
            groups: if enabled { groups.max(1) } else { 1 },
        }
    }

    /// Whether the map is the identity.
    pub fn is_identity(&self) -> bool {
        self.groups <= 1 || self.height <= 1
    }

    /// Number of logical pixels, `width · height` (as `u64`, never overflowing).
    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    fn g(&self) -> u32 {
        self.groups.max(1)
    }

    /// The logical row of physical row `y` (`y < height`).
    pub fn logical_row(&self, y: u32) -> u32 {
        let g = self.g();
        let (base, rem) = (self.height / g, self.height % g);
        let r = y % g;
        // Rows before group r: r groups of `base` rows, plus one extra for each of the
        // first `rem` groups.
        (r * base + r.min(rem)).wrapping_add(y / g)
    }

    /// The physical row of logical row `l` (`l < height`); inverse of
    /// [`logical_row`](Self::logical_row).
    pub fn physical_row(&self, l: u32) -> u32 {
        let g = self.g();
        let (base, rem) = (self.height / g, self.height % g);
        // The first `rem` groups hold `base + 1` rows each.
        let big = rem as u64 * (base as u64 + 1);
        let (r, i) = if (l as u64) < big {
            (l / (base + 1), l % (base + 1))
        } else {
            // `base > 0` here whenever `l < height`; `max(1)` keeps bad input panic-free.
            let rest = l - big as u32;
            (rem + rest / base.max(1), rest % base.max(1))
        };
        i.wrapping_mul(g).wrapping_add(r)
    }

    /// The logical pixel index of physical pixel `(x, y)`.
    pub fn logical_index(&self, x: u32, y: u32) -> u64 {
        self.logical_row(y) as u64 * self.width as u64 + x as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn five_rows_two_groups() {
        let il = Interlace::new(3, 5, 2, true);
        let order: Vec<u32> = (0..5).map(|l| il.physical_row(l)).collect();
        assert_eq!(order, [0, 2, 4, 1, 3]);
        assert_eq!(il.logical_row(1), 3);
        assert_eq!(il.logical_index(2, 1), 11);
    }

    #[test]
    fn disabled_is_identity() {
        let il = Interlace::new(4, 9, 3, false);
        assert_eq!(il.groups, 1);
        assert!(il.is_identity());
        for y in 0..9 {
            assert_eq!(il.logical_row(y), y);
            assert_eq!(il.physical_row(y), y);
        }
        assert_eq!(Interlace::new(4, 9, 0, true).groups, 1);
    }

    proptest! {
        #[test]
        fn rows_are_inverse_permutations(
            height in 1u32..300,
            groups in 0u32..40,
            enabled in any::<bool>(),
        ) {
            let il = Interlace::new(7, height, groups, enabled);
            let mut seen = vec![false; height as usize];
            for y in 0..height {
                let l = il.logical_row(y);
                prop_assert!(l < height);
                prop_assert!(!seen[l as usize], "logical row {} hit twice", l);
                seen[l as usize] = true;
                prop_assert_eq!(il.physical_row(l), y);
            }
            // Logical order: groups in turn, each ascending.
            let g = il.groups;
            let order: Vec<u32> = (0..height).map(|l| il.physical_row(l)).collect();
            let mut want: Vec<u32> = (0..height).collect();
            want.sort_by_key(|&y| (y % g, y));
            prop_assert_eq!(order, want);
        }
    }
}
