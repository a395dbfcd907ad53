//! Independent jobs of one frame (the markers' measurements) spread over threads, results in
//! the jobs' order.

use std::sync::atomic::{AtomicUsize, Ordering};

/// The threads to run `jobs` jobs on for a `threads` setting (0 = every core the system
/// offers): never more than the jobs, at least one.
pub(crate) fn thread_count(threads: usize, jobs: usize) -> usize {
    let asked = match threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => n,
    };
    asked.min(jobs).max(1)
}

/// `job(worker, item)` for every item, each of the `workers` (one task each on rayon's pool,
/// whose threads outlive the call; their per-worker state, such as a phase engine) taking the
/// next item not yet taken, so that costly items spread over the threads wherever they sit in
/// the list. The results come back in the items' order, the sequential result whatever the
/// number of workers; `None` when a job panicked.
pub(crate) fn map_in_order<W, T, R>(
    workers: &mut [W],
    items: &[T],
    job: impl Fn(&mut W, &T) -> R + Sync,
) -> Option<Vec<R>>
where
    W: Send,
    T: Sync,
    R: Send,
{
    let next = AtomicUsize::new(0);
    // Takes items from the shared queue: (item index, result) pairs.
    let take_and_run = |worker: &mut W| {
        let mut done = Vec::new();
        loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            let Some(item) = items.get(k) else {
                return done;
            };
            done.push((k, job(worker, item)));
        }
    };
    let mut results: Vec<(usize, R)> = match workers {
        [] => return (items.is_empty()).then(Vec::new),
        [only] => take_and_run(only),
        _ => {
            // rayon's pool: its threads live from frame to frame, and with them their caches.
            let done = std::sync::Mutex::new(Vec::with_capacity(items.len()));
            let run_all = || {
                rayon::scope(|s| {
                    for worker in workers.iter_mut() {
                        let (done, take_and_run) = (&done, &take_and_run);
                        s.spawn(move |_| {
                            let mine = take_and_run(worker);
                            done.lock().unwrap_or_else(|e| e.into_inner()).extend(mine);
                        });
                    }
                })
            };
            // A job that panicked panics the scope: reported as `None`, as documented.
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(run_all)).ok()?;
            done.into_inner().unwrap_or_else(|e| e.into_inner())
        }
    };
    results.sort_by_key(|(k, _)| *k);
    Some(results.into_iter().map(|(_, r)| r).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_keep_the_items_order_whatever_the_workers() {
        let items: Vec<u64> = (0..50).collect();
        for n in 1..=4 {
            let mut workers = vec![0usize; n];
            let out = map_in_order(&mut workers, &items, |count, &v| {
                *count += 1;
                (v, v * v)
            })
            .unwrap();
            assert_eq!(out, items.iter().map(|&v| (v, v * v)).collect::<Vec<_>>());
            assert_eq!(workers.iter().sum::<usize>(), items.len());
        }
        assert_eq!(map_in_order(&mut [(); 0], &items, |_, _| ()), None);
        let panicking = map_in_order(&mut [(); 2], &items, |_, &v| {
            assert!(v != 7, "job 7 fails");
            v
        });
        assert_eq!(panicking, None);
        assert_eq!(
            map_in_order(&mut [(); 0], &[0u8; 0], |_, _| ()),
            Some(vec![])
        );
    }
}
