//! Reading the next frame while the engine integrates this one: reading and decoding a 640 x
//! 480 PNG depth image takes about 1 ms (icl-livingroom1, whose log-odds frames at 0.05 m
//! integrate in 2.6 ms; BENCHMARKS.md session 42), and with a second core the engine leaves
//! that core idle between its parallel parts (a build of icl-livingroom1 on two threads: 0.71x
//! the time, session 31).

use std::sync::mpsc;

use crate::error::Result;

/// Calls `consume` with the readings `read(i)` of `indices` in order (each with its index),
/// read one ahead on a thread of their own when the thread pool has more than one thread (one
/// reading waits, read, besides the one being integrated); on one thread, read in turn, so
/// that `--threads 1` uses one core. Reading stops at the first error, which is passed on, and
/// when `consume` returns early. (A reader that panicked ends the readings early, and the
/// panic is raised again when `consume` returns.)
pub fn read_ahead<T: Send, R>(
    indices: &[usize],
    read: impl Fn(usize) -> Result<T> + Sync,
    consume: impl FnOnce(&mut dyn Iterator<Item = Result<(usize, T)>>) -> R,
) -> R {
    if rayon::current_num_threads() <= 1 || indices.len() <= 1 {
        let mut failed = false;
        return consume(&mut indices.iter().map_while(|&i| {
            (!failed).then(|| {
                let reading = read(i).map(|r| (i, r));
                failed = reading.is_err();
                reading
            })
        }));
    }
    std::thread::scope(|scope| {
        let (send, receive) = mpsc::sync_channel(0);
        let read = &read;
        scope.spawn(move || {
            for &i in indices {
                let reading = read(i).map(|r| (i, r));
                let failed = reading.is_err();
                // (A closed channel: the consumer stopped early.)
                if send.send(reading).is_err() || failed {
                    break;
                }
            }
        });
        // The receiver goes with `consume`'s iterator: a reader still reading ends at its
        // next send.
        consume(&mut receive.into_iter())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::Error;

    /// On any number of threads: every reading in order, an error passed on where it
    /// happened (and nothing read after it), and a consumer that stops early ends the reader.
    #[test]
    fn readings_come_in_order_and_stop_at_errors() {
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let indices: Vec<usize> = (0..50).rev().collect();
                let all: Vec<(usize, usize)> =
                    read_ahead(&indices, |i| Ok(i * 10), |it| it.map(|r| r.unwrap()).collect());
                assert_eq!(all, indices.iter().map(|&i| (i, i * 10)).collect::<Vec<_>>(), "{threads} threads");
                let read = std::sync::atomic::AtomicUsize::new(0);
                let got: Vec<Result<(usize, usize)>> = read_ahead(
                    &indices,
                    |i| {
                        read.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        if i == 40 { Err(Error::Invalid(format!("frame {i} is broken"))) } else { Ok(i) }
                    },
                    |it| it.collect(),
                );
                assert_eq!(got.len(), 10, "{threads} threads: frames 49..=41, then the error");
                assert!(got[..9].iter().all(Result::is_ok));
                assert!(got[9].as_ref().is_err_and(|e| e.to_string().contains("frame 40")));
                assert_eq!(read.load(std::sync::atomic::Ordering::Relaxed), 10, "{threads} threads");
                // A consumer that takes three and returns: the reader stops soon after.
                let read = std::sync::atomic::AtomicUsize::new(0);
                let first: Vec<usize> = read_ahead(
                    &indices,
                    |i| {
                        read.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        Ok(i)
                    },
                    |it| it.take(3).map(|r| r.unwrap().0).collect(),
                );
                assert_eq!(first, [49, 48, 47]);
                assert!(read.load(std::sync::atomic::Ordering::Relaxed) <= 6, "{threads} threads");
            })
        }
    }
}
