//! The Pareto front of (time, error) points and the check that the defaults sit on it.

/// Indices of the points no other point beats in both time and error (ties in both keep
/// the first), sorted by time.
pub fn front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    idx.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[a].1.total_cmp(&points[b].1))
            .then(a.cmp(&b))
    });
    let mut out = Vec::new();
    let mut best = f64::INFINITY;
    for i in idx {
        if points[i].1 < best {
            best = points[i].1;
            out.push(i);
        }
    }
    out
}

/// Whether point `d` is on the front "within `slack` in time at equal error": no point has
/// an error at most `d`'s and a time below `d`'s by more than the fraction `slack`. On
/// failure, the index of the point that beats it by the most time.
pub fn on_front(points: &[(f64, f64)], d: usize, slack: f64) -> Result<(), usize> {
    let (td, ed) = points[d];
    let mut worst: Option<usize> = None;
    for (i, &(t, e)) in points.iter().enumerate() {
        if i != d && e <= ed && t < td * (1.0 - slack) && worst.is_none_or(|w| t < points[w].0) {
            worst = Some(i);
        }
    }
    match worst {
        Some(w) => Err(w),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn front_of_a_small_set() {
        let p = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (4.0, 1.0), (2.0, 3.0)];
        assert_eq!(front(&p), vec![0, 1, 3]);
    }

    #[test]
    fn defaults_within_slack() {
        let p = [(1.0, 1.0), (0.97, 1.0), (0.5, 2.0)];
        // 3 % faster at equal error: inside a 5 % slack, outside a 1 % one.
        assert_eq!(on_front(&p, 0, 0.05), Ok(()));
        assert_eq!(on_front(&p, 0, 0.01), Err(1));
        // The faster point with a larger error does not count.
        assert_eq!(on_front(&p, 1, 0.05), Ok(()));
    }

    proptest! {
        #[test]
        fn front_points_are_undominated_and_the_rest_dominated(
            pts in proptest::collection::vec((0.0f64..10.0, 0.0f64..10.0), 1..40)
        ) {
            let f = front(&pts);
            for &i in &f {
                for (j, &(t, e)) in pts.iter().enumerate() {
                    let strictly = t <= pts[i].0 && e <= pts[i].1 && (t < pts[i].0 || e < pts[i].1);
                    prop_assert!(!strictly, "front point {i} dominated by {j}");
                }
                prop_assert!(on_front(&pts, i, 0.0).is_ok());
            }
            for j in 0..pts.len() {
                if !f.contains(&j) {
                    prop_assert!(f.iter().any(|&i| pts[i].0 <= pts[j].0 && pts[i].1 <= pts[j].1));
                }
            }
        }
    }
}
