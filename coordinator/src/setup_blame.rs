//! Who is to blame when a set-up attempt fails: the coordinator's rule, without I/O.
//!
//! Each worker of the attempt answers `Ready` or `Failed` (naming the peers it could not
//! mesh with) or stays silent. A worker that hung never answers, and its peers fail naming
//! it; a worker that cannot reach anyone fails naming all its peers, and they all fail
//! naming it. [`judge`] turns the answers so far into what the coordinator does next.

/// A worker's answer to the current set-up so far.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Answer {
    /// No answer yet.
    Waiting,
    /// Meshed and ready.
    Ready,
    /// Failed: why, and the peers (ranks) it could not mesh with.
    Failed(String, Vec<u32>),
}

/// A worker to give up on, and the failure that named it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Blamed {
    /// Its rank.
    pub rank: u32,
    /// The first worker whose failure named it.
    pub by: u32,
    /// That failure's message.
    pub message: String,
    /// How many failures named it.
    pub count: usize,
    /// It was still silent (hung), rather than named most among workers that all answered.
    pub silent: bool,
}

/// What the coordinator does next with a set-up attempt.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Wait for more answers.
    Wait,
    /// Every worker is ready.
    Ready,
    /// Give these up and set up the rest again.
    GiveUp(Vec<Blamed>),
    /// The set-up failed in a way no loss explains: the first failure (rank, message).
    Fail(u32, String),
}

/// Judges the answers of the workers in `slots` (`answers` indexed by rank; `fresh`: the
/// newcomers of this set-up, replacements that joined a running sequence).
///
/// * Some workers silent and every one of them named by a failure: they hung; give them up.
/// * Everyone answered and every failure names peers: the worker named most is the one
///   that could not mesh (an unreachable worker blames its peers too, but they all blame
///   it). It is given up if named at least twice, or if it is a newcomer (ties go to a
///   newcomer: the run was meshing before it came). A newcomer never fails the run.
/// * Everyone answered and some failure names no peer, or nobody stands out: the set-up
///   failed (the first failure).
pub fn judge(slots: &[u32], answers: &[Answer], fresh: &[u32]) -> Verdict {
    let answer = |r: u32| answers.get(r as usize).unwrap_or(&Answer::Waiting);
    let waiting: Vec<u32> = slots
        .iter()
        .copied()
        .filter(|&r| *answer(r) == Answer::Waiting)
        .collect();
    let failures: Vec<(u32, &String, &Vec<u32>)> = slots
        .iter()
        .filter_map(|&r| match answer(r) {
            Answer::Failed(m, s) => Some((r, m, s)),
            _ => None,
        })
        .collect();
    let named_by = |r: u32| failures.iter().find(|f| f.2.contains(&r));
    let count = |r: u32| failures.iter().filter(|f| f.2.contains(&r)).count();
    let blamed = |r: u32, silent: bool| {
        named_by(r).map(|(by, m, _)| Blamed {
            rank: r,
            by: *by,
            message: (*m).clone(),
            count: count(r),
            silent,
        })
    };
    if !waiting.is_empty() {
        if failures.is_empty() {
            return Verdict::Wait;
        }
        // Every worker still waiting is one a failed peer could not mesh with: it hung,
        // and the peers said so before the deadline.
        let hung: Option<Vec<Blamed>> = waiting.iter().map(|&r| blamed(r, true)).collect();
        return match hung {
            Some(h) => Verdict::GiveUp(h),
            None => Verdict::Wait,
        };
    }
    let Some(first) = failures.first() else {
        return Verdict::Ready;
    };
    if failures.iter().all(|f| !f.2.is_empty()) {
        let worst = slots
            .iter()
            .copied()
            .max_by_key(|&r| (count(r), fresh.contains(&r), r));
        if let Some(w) = worst.filter(|&w| count(w) >= 2 || (count(w) >= 1 && fresh.contains(&w))) {
            return Verdict::GiveUp(vec![blamed(w, false).expect("named at least once")]);
        }
    }
    Verdict::Fail(first.0, first.1.clone())
}

#[cfg(test)]
mod tests {
    use super::*;
    use Answer::*;

    fn failed(peers: &[u32]) -> Answer {
        Failed(format!("could not reach {peers:?}"), peers.to_vec())
    }

    fn given_up(v: &Verdict) -> Vec<u32> {
        match v {
            Verdict::GiveUp(b) => b.iter().map(|b| b.rank).collect(),
            _ => Vec::new(),
        }
    }

    #[test]
    fn waiting_ready_and_plain_failures() {
        let slots = [0, 1, 2];
        assert_eq!(judge(&slots, &[Ready, Waiting, Ready], &[]), Verdict::Wait);
        assert_eq!(judge(&slots, &[Ready, Ready, Ready], &[]), Verdict::Ready);
        // A failure that names no peer fails the set-up.
        let v = judge(
            &slots,
            &[Ready, Failed("bad scene".into(), vec![]), Ready],
            &[],
        );
        assert_eq!(v, Verdict::Fail(1, "bad scene".into()));
        // Ranks outside the attempt are not judged.
        assert_eq!(
            judge(&[0, 2], &[Ready, Waiting, Ready], &[]),
            Verdict::Ready
        );
    }

    #[test]
    fn silent_workers_named_by_the_failures_hung() {
        let slots = [0, 1, 2, 3];
        let v = judge(&slots, &[failed(&[2]), Ready, Waiting, Ready], &[]);
        assert_eq!(given_up(&v), vec![2]);
        let Verdict::GiveUp(b) = &v else { panic!() };
        assert!(b[0].silent && b[0].by == 0 && b[0].count == 1);
        // A silent worker nobody named: wait (the deadline decides).
        let v = judge(&slots, &[failed(&[2]), Ready, Waiting, Waiting], &[]);
        assert_eq!(v, Verdict::Wait);
    }

    #[test]
    fn when_everyone_failed_blaming_peers_the_most_blamed_is_given_up() {
        // Rank 3 cannot reach anyone: it blames everyone, everyone blames it.
        let slots = [0, 1, 2, 3];
        let answers = [failed(&[3]), failed(&[3]), failed(&[3]), failed(&[0, 1, 2])];
        let v = judge(&slots, &answers, &[]);
        assert_eq!(given_up(&v), vec![3]);
        let Verdict::GiveUp(b) = &v else { panic!() };
        assert_eq!((b[0].count, b[0].by, b[0].silent), (3, 0, false));
        // Two workers that blame only each other: named once each, no one stands out,
        // unless one is a newcomer, which goes (the run meshed before it came).
        let answers = [failed(&[1]), failed(&[0]), Ready];
        assert_eq!(
            judge(&[0, 1, 2], &answers, &[]),
            Verdict::Fail(0, "could not reach [1]".into())
        );
        assert_eq!(given_up(&judge(&[0, 1, 2], &answers, &[0])), vec![0]);
        assert_eq!(given_up(&judge(&[0, 1, 2], &answers, &[1])), vec![1]);
        // Ties in count go to a newcomer.
        let answers = [failed(&[1, 2]), failed(&[0, 2]), failed(&[0, 1])];
        assert_eq!(given_up(&judge(&[0, 1, 2], &answers, &[1])), vec![1]);
        // A newcomer nobody named is not given up for being new.
        let answers = [failed(&[1]), failed(&[0]), Ready];
        assert_eq!(
            judge(&[0, 1, 2], &answers, &[2]),
            Verdict::Fail(0, "could not reach [1]".into())
        );
        // Failures naming only ranks outside the attempt: nobody to blame, no panic.
        let answers = [failed(&[7]), failed(&[7]), Ready];
        assert_eq!(
            judge(&[0, 1, 2], &answers, &[0]),
            Verdict::Fail(0, "could not reach [7]".into())
        );
    }
}
