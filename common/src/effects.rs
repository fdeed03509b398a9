//! The effects a frame uses, and the code path that renders it.
//!
//! Both casters are compiled once per *effect set* they may meet, so that an effect the
//! scene does not use costs nothing: the CPU monomorphises its ray and sample loops over the
//! set (const generics), the GPU builds one pipeline per set (WGSL override constants). The
//! set a frame runs with is its own effects, or every effect when `render.variant =
//! "general"` forces the one path that handles everything (the baseline the feature-cost
//! benchmark measures against).
//!
//! This module is the vocabulary: the bits, their names, and the rule that a set is
//! *closed* (an effect implies the ones it needs, e.g. several volumes imply a volume).

use serde::{Deserialize, Serialize};

/// A set of effects, as bits.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct EffectSet(u8);

impl EffectSet {
    /// No effect: nothing to draw.
    pub const NONE: EffectSet = EffectSet(0);
    /// At least one volume is marched (a volume whose transfer function shows nothing is
    /// not; its slices may still show).
    pub const VOLUME: EffectSet = EffectSet(1);
    /// Several volumes: rays are cut at their boxes and overlapping samples mixed.
    pub const VOLUMES: EffectSet = EffectSet(2);
    /// Horizons (height-field surfaces).
    pub const HORIZONS: EffectSet = EffectSet(4);
    /// Lambert headlight shading of horizons.
    pub const LIGHTING: EffectSet = EffectSet(8);
    /// Slices through volumes.
    pub const SLICES: EffectSet = EffectSet(16);
    /// Gradient (Blinn-Phong) shading of volume samples.
    pub const SHADING: EffectSet = EffectSet(32);
    /// Pre-integrated classification of volume segments.
    pub const PREINTEGRATED: EffectSet = EffectSet(64);
    /// Every effect: the general path.
    pub const ALL: EffectSet = EffectSet(127);

    /// Each effect with its name, in the order names are printed.
    pub const NAMED: [(EffectSet, &'static str); 7] = [
        (Self::VOLUME, "volume"),
        (Self::VOLUMES, "volumes"),
        (Self::HORIZONS, "horizons"),
        (Self::LIGHTING, "lighting"),
        (Self::SLICES, "slices"),
        (Self::SHADING, "shading"),
        (Self::PREINTEGRATED, "preintegrated"),
    ];

    /// The set's bits.
    pub const fn bits(self) -> u8 {
        self.0
    }

    /// The set of these bits (bits past [`ALL`](Self::ALL) are dropped).
    pub const fn from_bits(bits: u8) -> Self {
        EffectSet(bits & Self::ALL.0)
    }

    /// Whether every effect of `other` is in the set.
    pub const fn contains(self, other: EffectSet) -> bool {
        self.0 & other.0 == other.0
    }

    /// Both sets' effects.
    #[must_use]
    pub const fn union(self, other: EffectSet) -> Self {
        EffectSet(self.0 | other.0)
    }

    /// The set with `other`'s effects removed.
    #[must_use]
    pub const fn without(self, other: EffectSet) -> Self {
        EffectSet(self.0 & !other.0)
    }

    /// The set with `e` added when `on`.
    #[must_use]
    pub const fn with_if(self, e: EffectSet, on: bool) -> Self {
        if on {
            self.union(e)
        } else {
            self
        }
    }

    /// The set plus what its effects need: several volumes, shading and pre-integration
    /// need a volume; lighting needs horizons.
    #[must_use]
    pub const fn closed(self) -> Self {
        let mut s = self;
        if s.0 & (Self::VOLUMES.0 | Self::SHADING.0 | Self::PREINTEGRATED.0) != 0 {
            s.0 |= Self::VOLUME.0;
        }
        if s.0 & Self::LIGHTING.0 != 0 {
            s.0 |= Self::HORIZONS.0;
        }
        s
    }

    /// Whether the set holds everything its effects need.
    pub const fn is_closed(self) -> bool {
        self.closed().0 == self.0
    }
}

impl std::fmt::Display for EffectSet {
    /// `volume+horizons+lighting`, or `none`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.0 == 0 {
            return f.write_str("none");
        }
        let mut first = true;
        for (e, name) in Self::NAMED {
            if self.contains(e) {
                if !first {
                    f.write_str("+")?;
                }
                f.write_str(name)?;
                first = false;
            }
        }
        Ok(())
    }
}

/// The code a frame ran: the effects it uses and the effects its code path has compiled
/// in (a superset: equal when specialised, [`EffectSet::ALL`] on the general path).
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Variant {
    /// What the frame draws.
    pub effects: EffectSet,
    /// What its code path handles.
    pub compiled: EffectSet,
}

impl Variant {
    /// The frame's code: specialised to `effects`, or with `extra` effects compiled in too
    /// (closed, so the path can run them).
    pub fn new(effects: EffectSet, extra: EffectSet) -> Self {
        Variant {
            effects,
            compiled: effects.union(extra).closed(),
        }
    }

    /// Whether the code path is the general one (every effect compiled in).
    pub fn is_general(self) -> bool {
        self.compiled == EffectSet::ALL
    }

    /// `specialised` (only the frame's effects), `general` (every effect), or the effects
    /// compiled in beyond the frame's, e.g. `specialised+shading`.
    pub fn path_name(self) -> String {
        if self.is_general() {
            "general".into()
        } else if self.compiled == self.effects {
            "specialised".into()
        } else {
            format!("specialised+{}", self.compiled.without(self.effects))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_set_prints_a_distinct_name() {
        let names: std::collections::HashSet<String> = (0..=EffectSet::ALL.bits())
            .map(|b| EffectSet::from_bits(b).to_string())
            .collect();
        assert_eq!(names.len(), EffectSet::ALL.bits() as usize + 1);
        assert_eq!(EffectSet::NONE.to_string(), "none");
        assert_eq!(
            EffectSet::ALL.to_string(),
            "volume+volumes+horizons+lighting+slices+shading+preintegrated"
        );
    }

    #[test]
    fn closure_adds_what_effects_need() {
        assert_eq!(
            EffectSet::SHADING.closed(),
            EffectSet::SHADING.union(EffectSet::VOLUME)
        );
        assert_eq!(
            EffectSet::VOLUMES.closed(),
            EffectSet::VOLUMES.union(EffectSet::VOLUME)
        );
        assert_eq!(
            EffectSet::LIGHTING.closed(),
            EffectSet::LIGHTING.union(EffectSet::HORIZONS)
        );
        assert!(EffectSet::ALL.is_closed());
        assert!(!EffectSet::PREINTEGRATED.is_closed());
        let closed = (0..=EffectSet::ALL.bits())
            .filter(|&b| EffectSet::from_bits(b).is_closed())
            .count();
        // Volume: 2 (one or several) × 2 × 2 (shading, pre-integration); no volume: 1;
        // times horizons (none, unlit, lit) × slices (2).
        assert_eq!(closed, (2 * 2 * 2 + 1) * 3 * 2);
    }

    #[test]
    fn a_variant_names_its_path() {
        let e = EffectSet::VOLUME.union(EffectSet::HORIZONS);
        assert_eq!(Variant::new(e, EffectSet::NONE).path_name(), "specialised");
        assert_eq!(Variant::new(e, EffectSet::ALL).path_name(), "general");
        assert_eq!(
            Variant::new(e, EffectSet::LIGHTING).path_name(),
            "specialised+lighting"
        );
        assert_eq!(
            Variant::new(EffectSet::HORIZONS, EffectSet::SHADING).compiled,
            EffectSet::HORIZONS
                .union(EffectSet::SHADING)
                .union(EffectSet::VOLUME)
        );
    }
}
