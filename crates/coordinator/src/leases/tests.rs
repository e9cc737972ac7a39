//! The lease table's rules, without clocks or sockets.

use super::*;
use tessera_request::placement::{Placement, Tag};

const LEASE: u64 = 10_000;

fn drain(table: &mut LeaseTable, render: u64) -> Vec<(u32, u32)> {
    let mut done = Vec::new();
    while let Some(l) = table.lease("w", 3, 0, LEASE) {
        assert_eq!(l.render, render);
        let Completion::Accepted(l) = table.complete(l.lease_id, "w", 1) else { panic!("ignored") };
        done.extend((l.first..l.first + l.count).map(|p| (l.tile, p)));
    }
    done.sort();
    done
}

#[test]
fn every_pass_is_handed_out_and_merged_once() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[5; 4], &[]);
    let done = drain(&mut t, 1);
    let expected: Vec<(u32, u32)> = (0..4).flat_map(|tile| (0..5).map(move |p| (tile, p))).collect();
    assert_eq!(done, expected);
    assert!(t.is_complete(1));
}

#[test]
fn duplicates_and_late_results_are_ignored() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[2; 1], &[]);
    let a = t.lease("a", 1, 0, LEASE).unwrap();
    assert!(matches!(t.complete(a.lease_id, "a", 5), Completion::Accepted(_)));
    assert_eq!(t.complete(a.lease_id, "a", 6), Completion::Ignored(Ignored::Duplicate), "duplicate");
    let b = t.lease("b", 1, 10, LEASE).unwrap();
    // b's lease expires; its pass goes to c; b's late result is ignored.
    let expired = t.expire(10 + LEASE);
    assert_eq!(expired.len(), 1);
    assert_eq!((t.passes_leased, t.passes_expired), (2, 1));
    let c = t.lease("c", 1, 10 + LEASE + 1, LEASE).unwrap();
    assert_eq!((c.tile, c.first), (b.tile, b.first));
    assert_eq!(t.complete(b.lease_id, "b", 10 + LEASE + 2), Completion::Ignored(Ignored::Late), "late");
    assert!(matches!(t.complete(c.lease_id, "c", 10 + LEASE + 3), Completion::Accepted(_)));
    assert!(t.is_complete(1));
    assert_eq!(t.progress(1), Some((2, 2)));
}

#[test]
fn heartbeats_keep_leases_alive_and_name_dead_ones() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[1; 2], &[]);
    let a = t.lease("a", 1, 0, LEASE).unwrap();
    assert!(t.heartbeat("a", &[a.lease_id], LEASE - 1, LEASE).is_empty());
    assert!(t.expire(LEASE + 1).is_empty(), "the heartbeat extended the lease");
    assert_eq!(t.heartbeat("a", &[999], LEASE + 2, LEASE), vec![999]);
    assert_eq!(t.heartbeat("intruder", &[a.lease_id], LEASE + 3, LEASE), vec![a.lease_id]);
    assert_eq!(t.complete(a.lease_id, "intruder", LEASE + 4), Completion::Ignored(Ignored::WrongWorker));
}

#[test]
fn released_leases_go_back_to_the_queue_at_once() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[2; 1], &[]);
    let a = t.lease("a", 1, 0, LEASE).unwrap();
    assert_eq!(t.release("intruder", &[a.lease_id]), 0, "only the holder may release");
    assert_eq!(t.release("a", &[a.lease_id, 999]), 1);
    assert_eq!(t.release("a", &[a.lease_id]), 0, "released once");
    let b = t.lease("b", 1, 1, LEASE).unwrap();
    assert_eq!((b.tile, b.first), (a.tile, a.first), "the released pass is first in line, long before expiry");
    assert_eq!(
        t.complete(a.lease_id, "a", 2),
        Completion::Ignored(Ignored::Released),
        "a released lease cannot complete"
    );
    assert!(matches!(t.complete(b.lease_id, "b", 3), Completion::Accepted(_)));
    assert_eq!((t.passes_released, t.passes_expired), (1, 0));
}

#[test]
fn restart_skips_passes_already_merged() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[2; 2], &[(0, 0), (1, 1)]);
    let done = drain(&mut t, 1);
    assert_eq!(done, vec![(0, 1), (1, 0)]);
}

#[test]
fn higher_priority_first_then_oldest_first() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[1; 3], &[]);
    t.add_render(2, 0, &[1; 3], &[]);
    t.add_render(3, 5, &[1; 2], &[]);
    let order: Vec<u64> = (0..8).map(|i| t.lease("w", 1, i, LEASE).unwrap().render).collect();
    assert_eq!(order, [3, 3, 1, 1, 1, 2, 2, 2], "a later render waits for the one before it");
}

#[test]
fn adaptive_rounds_extend_one_tile() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[1, 1], &[]);
    drain(&mut t, 1);
    assert!(t.is_complete(1));
    assert_eq!(t.progress(1), Some((2, 2)));
    t.extend_tile(1, 1, 1, 4);
    assert!(!t.is_complete(1));
    assert_eq!(drain(&mut t, 1), vec![(1, 1), (1, 2), (1, 3)]);
    assert_eq!(t.progress(1), Some((5, 5)));
}

#[test]
fn jobs_are_runs_of_consecutive_passes_of_one_tile() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[10; 1], &[(0, 4)]);
    let l = t.lease("w", 8, 0, LEASE).unwrap();
    assert_eq!((l.first, l.count), (0, 1), "a tile's first pass goes alone");
    let l = t.lease("w", 8, 0, LEASE).unwrap();
    assert_eq!((l.first, l.count), (1, 3), "stops at the merged pass 4");
    let l = t.lease("w", 8, 0, LEASE).unwrap();
    assert_eq!((l.first, l.count), (5, 5));
}

#[test]
fn a_huge_budget_costs_nothing_until_leased() {
    // 65,536 tiles x 2^20 passes (2^36 passes) once built one entry per pass and froze the
    // coordinator; the lazy queue holds one entry per tile.
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &vec![1 << 20; 1 << 16], &[]);
    assert_eq!(t.progress(1), Some((0, 1 << 36)));
    let a = t.lease("w", 4, 0, LEASE).unwrap();
    let b = t.lease("w", 4, 0, LEASE).unwrap();
    assert_eq!((a.tile, a.first, a.count), (0, 0, 1));
    assert_eq!((b.tile, b.first, b.count), (1, 0, 1), "pass-major: every tile's first pass comes first");
    assert_eq!(t.pending_passes(), (1 << 36) - 2);
}

#[test]
fn every_tile_gets_its_first_pass_before_any_gets_a_second() {
    // Long jobs (64 passes) once gave tile 0 its whole budget before tile 1 had anything:
    // the preview filled as a strip from the top.
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[100; 6], &[]);
    let first: Vec<(u32, u32, u32)> =
        (0..6).map(|_| t.lease("w", 64, 0, LEASE).unwrap()).map(|l| (l.tile, l.first, l.count)).collect();
    assert_eq!(first, (0..6).map(|tile| (tile, 0, 1)).collect::<Vec<_>>());
    let next = t.lease("w", 64, 0, LEASE).unwrap();
    assert_eq!((next.tile, next.first, next.count), (0, 1, 64), "then long jobs");
}

#[test]
fn every_ignored_result_says_why() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[4; 2], &[]);
    let done = t.lease("a", 1, 0, LEASE).unwrap();
    assert!(matches!(t.complete(done.lease_id, "a", 1), Completion::Accepted(_)));
    let expired = t.lease("a", 1, 0, LEASE).unwrap();
    let released = t.lease("a", 1, 0, LEASE).unwrap();
    t.release("a", &[released.lease_id]);
    t.add_render(2, 1, &[4; 1], &[]);
    let other = t.lease("a", 1, 0, LEASE).unwrap();
    assert_eq!(other.render, 2, "the higher priority");
    t.remove_render(2);
    let held = t.lease("a", 1, LEASE + 1, LEASE).unwrap();
    let why = |t: &mut LeaseTable, id: u64, worker: &str| match t.complete(id, worker, LEASE + 2) {
        Completion::Ignored(why) => why,
        Completion::Accepted(l) => panic!("accepted {l:?}"),
    };
    assert_eq!(why(&mut t, done.lease_id, "a"), Ignored::Duplicate);
    assert_eq!(why(&mut t, expired.lease_id, "a"), Ignored::Late);
    assert_eq!(why(&mut t, released.lease_id, "a"), Ignored::Released);
    assert_eq!(why(&mut t, other.lease_id, "a"), Ignored::RenderEnded);
    assert_eq!(why(&mut t, held.lease_id, "b"), Ignored::WrongWorker);
    assert_eq!(why(&mut t, 10_000, "a"), Ignored::Unknown);
}

#[test]
fn checks_go_first_to_other_workers_and_come_back_when_their_lease_ends() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[2; 1], &[]);
    let a = t.lease("a", 1, 0, LEASE).unwrap();
    assert!(matches!(t.complete(a.lease_id, "a", 1), Completion::Accepted(_)));
    t.add_check(1, a.tile, a.first, a.count, vec!["a".into()]);
    let own = t.lease("a", 1, 2, LEASE).unwrap();
    assert_eq!((own.check.clone(), own.first), (None, 1), "a checks none of its own results");
    let b = t.lease("b", 1, 3, LEASE).unwrap();
    assert_eq!((b.check.clone(), b.first), (Some(vec!["a".to_string()]), 0), "a check goes before any pass");
    assert_eq!(t.passes_in_flight(), 1, "a check is not a pass to merge");
    t.expire(3 + LEASE);
    let c = t.lease("c", 1, 4 + LEASE, LEASE).unwrap();
    assert_eq!((c.check.is_some(), c.first), (true, 0), "an expired check comes back first");
    assert!(matches!(t.complete(c.lease_id, "c", 5 + LEASE), Completion::Accepted(_)));
    assert_eq!(t.progress(1), Some((1, 2)), "a check's result merges no pass");
    assert_eq!(t.pending_checks(), 0);
    t.add_check(1, 0, 0, 1, vec!["a".into()]);
    t.remove_render(1);
    assert_eq!(t.pending_checks(), 0, "a render's checks go with it");
}

#[test]
fn a_blocked_workers_leases_go_back_in_line() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[2; 1], &[]);
    let l = t.lease("liar", 1, 0, LEASE).unwrap();
    assert_eq!(t.drop_worker("liar"), 1);
    assert_eq!(t.complete(l.lease_id, "liar", 1), Completion::Ignored(Ignored::Blocked));
    let again = t.lease("b", 1, 2, LEASE).unwrap();
    assert_eq!((again.tile, again.first), (l.tile, l.first));
}

#[test]
fn gaps_left_by_a_restart_are_handed_out_first() {
    let mut t = LeaseTable::new();
    // Passes 0-3 and 8-9 were merged; 4-7 were in flight when the coordinator died.
    let merged: Vec<(u32, u32)> = [0, 1, 2, 3, 8, 9].iter().map(|&p| (0, p)).collect();
    t.add_render(1, 0, &[12], &merged);
    assert_eq!(t.progress(1), Some((6, 12)));
    let l = t.lease("w", 8, 0, LEASE).unwrap();
    assert_eq!((l.first, l.count), (4, 4));
    let l = t.lease("w", 8, 0, LEASE).unwrap();
    assert_eq!((l.first, l.count), (10, 2));
}

#[test]
fn a_paused_group_gets_no_jobs_until_resumed_and_priority_changes_the_order() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[4], &[]);
    t.add_to_group(2, 2, 0, &[4], &[]);
    t.add_to_group(3, 2, 0, &[4], &[]);
    assert!(t.steer(2, None, Some(true)));
    assert!(!t.steer(9, None, Some(true)), "no such group");
    assert_eq!(t.steering(2), Some((0, true)));
    for _ in 0..4 {
        assert_eq!(t.lease("w", 1, 0, LEASE).unwrap().render, 1, "only the render not paused");
    }
    assert_eq!(t.lease("w", 1, 0, LEASE), None, "the paused sequence waits");
    // A check of a paused render waits too.
    t.add_check(2, 0, 0, 1, vec!["x".into()]);
    assert_eq!(t.lease("w", 1, 0, LEASE), None);
    t.steer(2, Some(5), Some(false));
    let l = t.lease("w", 1, 0, LEASE).unwrap();
    assert!(l.check.is_some() && l.render == 2, "the check goes first once resumed");
    t.add_render(4, 0, &[4], &[]);
    assert_eq!(t.lease("w", 1, 0, LEASE).unwrap().render, 2, "priority 5 before 0");
    t.steer(2, Some(-1), None);
    assert_eq!(t.lease("w", 1, 0, LEASE).unwrap().render, 4, "lowered below the newer render");
}

#[test]
fn a_pause_now_hands_back_the_groups_leases() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[4], &[]);
    t.add_render(2, 0, &[4], &[]);
    let a = t.lease("w", 2, 0, LEASE).unwrap();
    let b = t.lease("w", 2, 0, LEASE).unwrap();
    let c = t.lease("v", 2, 0, LEASE).unwrap();
    assert_eq!((a.render, b.render, c.render), (1, 1, 1));
    let other = t.lease("v", 2, 0, LEASE).unwrap();
    assert_eq!(other.render, 2);
    t.steer(1, None, Some(true));
    let ended = t.release_group(1);
    assert_eq!(ended.len(), 3, "render 1's leases, not render 2's");
    assert_eq!(t.passes_released, 4);
    assert!(t.get(other.lease_id).is_some());
    assert_eq!(t.complete(a.lease_id, "w", 1), Completion::Ignored(Ignored::Released));
    assert_eq!(t.lease("w", 2, 0, LEASE).unwrap().render, 2);
    t.steer(1, None, Some(false));
    let again = t.lease("w", 1, 0, LEASE).unwrap();
    assert_eq!((again.render, again.first), (1, 0), "its passes came back in line");
}

fn placed(pool: &str, requires: &[&str]) -> Placement {
    Placement::parse(pool, &requires.iter().map(|r| r.to_string()).collect::<Vec<_>>()).unwrap()
}

/// A render of a pool goes only to workers of that pool, and to them before renders of no
/// pool, whatever the priorities; requirements are checked against the worker's tags; checks
/// of a placed render wait for a worker that fits too.
#[test]
fn pools_and_requirements_decide_who_may_take_a_render() {
    let mut t = LeaseTable::new();
    t.add_render(1, 9, &[4], &[]);
    t.add_render(2, 0, &[4], &[]);
    t.place(2, "", &placed("gpu", &[]));
    t.add_render(3, 0, &[4], &[]);
    t.place(3, "", &placed("", &["mem>=32G"]));
    let (big, small) = ([Tag::parse("mem=64G").unwrap()], [Tag::parse("mem=8G").unwrap()]);
    let gpu = Asker { worker: "g", pool: "gpu", tags: &small };
    let plain = Asker { worker: "p", pool: "", tags: &small };
    let roomy = Asker { worker: "r", pool: "", tags: &big };
    let lease = |t: &mut LeaseTable, a: Asker| t.lease_except(a, 1, 0, LEASE, None, |_| false).map(|l| l.render);
    assert_eq!(lease(&mut t, gpu), Some(2), "its own pool's render before a higher priority of no pool");
    for _ in 0..4 {
        assert_eq!(lease(&mut t, plain), Some(1), "never the gpu render, nor the one needing 32G");
    }
    assert_eq!(lease(&mut t, plain), None);
    assert_eq!(lease(&mut t, roomy), Some(3));
    t.add_check(2, 0, 0, 1, vec!["g".into()]);
    assert_eq!(lease(&mut t, roomy), Some(3), "a check of the gpu render is not for a worker of no pool");
}

/// Workers are shared between owners by weight while several owners' renders wait (within
/// 10 % of the weights over 6,000 leases of 60 simulated workers, each job taking a random
/// time), priorities order one owner's renders only, and one owner alone gets every worker.
#[test]
fn owners_share_the_farm_by_weight_and_one_alone_gets_all_of_it() {
    let mut t = LeaseTable::new();
    let owners = [("ann", 1.0), ("ben", 2.0), ("cat", 3.0)];
    t.set_weights(owners.iter().map(|&(o, w)| (o.to_string(), w)).collect());
    for (i, (owner, _)) in owners.iter().enumerate() {
        // Each owner has two renders; the first of ann's is urgent, which does not raise her share.
        for k in 0..2 {
            let id = (i * 2 + k + 1) as u64;
            t.add_render(id, if i == 0 && k == 0 { 100 } else { 0 }, &[1 << 20], &[]);
            t.place(id, owner, &Placement::default());
        }
    }
    let owner_of = |render: u64| owners[((render - 1) / 2) as usize].0;
    let workers: Vec<String> = (0..60).map(|w| format!("w{w}")).collect();
    let mut held: Vec<Option<JobLease>> = vec![None; workers.len()];
    let mut counts = std::collections::HashMap::<&str, u64>::new();
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut next = || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    for step in 0..6000u64 {
        // A random worker finishes its job (if it has one) and takes the next.
        let w = (next() % workers.len() as u64) as usize;
        if let Some(l) = held[w].take() {
            assert!(matches!(t.complete(l.lease_id, &workers[w], step), Completion::Accepted(_)));
        }
        let l = t.lease(&workers[w], 1, step, u64::MAX / 4).expect("work for everyone");
        if step >= 600 {
            *counts.entry(owner_of(l.render)).or_default() += 1;
        }
        held[w] = Some(l);
    }
    let total: u64 = counts.values().sum();
    for (owner, weight) in owners {
        let share = counts[owner] as f64 / total as f64;
        let expected = weight / 6.0;
        assert!((share - expected).abs() <= 0.1 * expected, "{owner}: {share:.3} of leases, {expected:.3} expected");
    }
    // Alone, an owner gets every worker.
    let mut alone = LeaseTable::new();
    alone.set_weights(owners.iter().map(|&(o, w)| (o.to_string(), w)).collect());
    alone.add_render(1, 0, &[1000], &[]);
    alone.place(1, "ann", &Placement::default());
    for w in &workers {
        assert_eq!(alone.lease(w, 1, 0, LEASE).map(|l| l.render), Some(1));
    }
    assert_eq!(alone.in_flight_by_owner()["ann"], 60);
}

/// A capped render hands out only passes below its cap (whole runs stop there), and after the
/// cap is lifted the rest, each pass once.
#[test]
fn a_cap_holds_passes_back_until_it_is_lifted() {
    let mut t = LeaseTable::new();
    t.add_to_group(1, 1, 0, &[6, 6], &[]);
    t.add_to_group(2, 1, 0, &[6], &[]);
    t.set_cap(1, Some(2));
    t.set_cap(2, Some(0));
    let mut below = Vec::new();
    while let Some(l) = t.lease("w", 8, 0, LEASE) {
        assert_eq!(l.render, 1, "render 2 is held back entirely");
        below.extend((l.first..l.first + l.count).map(|p| (l.tile, p)));
    }
    below.sort();
    assert_eq!(below, [(0, 0), (0, 1), (1, 0), (1, 1)]);
    t.set_cap(1, None);
    t.set_cap(2, None);
    let mut rest = 0;
    while let Some(l) = t.lease("w", 8, 0, LEASE) {
        assert!(l.render == 2 || l.first >= 2);
        rest += l.count;
    }
    assert_eq!(rest, 8 + 6);
}

#[test]
fn a_pilot_goes_first_paused_or_not_and_only_its_tiles_first_round() {
    let mut t = LeaseTable::new();
    t.add_render(1, 5, &[4; 3], &[]); // an earlier render of higher priority
    t.add_render(2, 0, &[2; 6], &[]); // the one quoted: its first round is 2 passes
    t.steer(2, None, Some(true));
    assert!(t.pilot(2, [1, 4], 2));
    assert!(!t.pilot(9, [0], 1), "no such render");
    let mut piloted = Vec::new();
    for _ in 0..4 {
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!(l.render, 2, "the pilot goes ahead of other work, though its render is paused");
        let Completion::Accepted(l) = t.complete(l.lease_id, "w", 1) else { panic!("ignored") };
        piloted.extend((l.first..l.first + l.count).map(|p| (l.tile, p)));
    }
    piloted.sort();
    assert_eq!(piloted, [(1, 0), (1, 1), (4, 0), (4, 1)], "the first round of the pilot's tiles, each once");
    // The pilot is done: the paused render waits and the other is served.
    for _ in 0..12 {
        let l = t.lease("w", 1, 0, LEASE).unwrap();
        assert_eq!(l.render, 1);
        t.complete(l.lease_id, "w", 1);
    }
    assert_eq!(t.lease("w", 1, 0, LEASE), None, "the quoted render stays paused after its pilot");
    // Resumed, it renders the rest and nothing of the pilot again.
    t.steer(2, None, Some(false));
    let rest = drain(&mut t, 2);
    assert_eq!(rest.len(), 12 - 4);
    assert!(rest.iter().all(|p| !piloted.contains(p)));
    assert!(t.is_complete(2));
}

#[test]
fn a_pilot_keeps_its_placement_and_takes_back_expired_passes() {
    let mut t = LeaseTable::new();
    t.add_render(1, 0, &[1; 2], &[]);
    t.place(1, "", &Placement::parse("gpu", &[]).unwrap());
    t.pilot(1, [0, 1], 1);
    assert_eq!(t.lease("w", 1, 0, LEASE), None, "a worker of no pool may not take a pool's pilot");
    let gpu = Asker { worker: "g", pool: "gpu", tags: &[] };
    let l = t.lease_except(gpu, 1, 0, LEASE, None, |_| false).unwrap();
    t.expire(LEASE + 1);
    let again = t.lease_except(gpu, 1, LEASE + 2, LEASE, None, |_| false).unwrap();
    assert_eq!((again.tile, again.first), (l.tile, l.first), "an expired pilot pass goes first again");
}
