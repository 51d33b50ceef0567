//! Getting a pool worker that waits behind the thread that started a parallel step onto a
//! core of its own.
//!
//! A frame's parallel steps each wake the thread pool's sleeping workers. Linux puts a woken
//! thread on the waker's core when it judges the machine busy (the other core running the
//! next frame's decoding, say), and the waker then runs on: the worker waits there up to a
//! scheduler tick (4 ms at 250 Hz) while the step runs on one thread, and on a two-core
//! machine the other core may meanwhile have gone idle. Traced on icl-livingroom-5 at 0.05 m
//! on two threads, the worker spent whole builds queued on the main thread's core, running
//! for microseconds at a time (BENCHMARKS.md, session 48).
//!
//! [`Step`] watches one step: each job of the step calls [`Step::job`] first. Workers mark that
//! they have run; once the step is [`WAIT`] old, the thread that started it moves each worker
//! that has not run yet off its own core: the worker's allowed cores are narrowed to exclude
//! this one, which makes the kernel move it if it is queued here, and given back at once. No
//! thread is bound to a core, and a process's own affinity (`taskset`) is kept: the narrowing
//! is within the worker's mask, which is then restored as it was. A worker queued elsewhere,
//! running, or asleep is not moved. Workers are known by their thread ids, which each records
//! the first time it runs a job of a step, or at its start ([`register_thread`], which a
//! pool's `start_handler` may call, so that they are known from the first frame); an id is
//! used only while it names a thread of this process. Steps are watched when they start on a
//! thread of a pool of two or more, on Linux; otherwise [`Step::job`] does nothing.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::time::{Duration, Instant};

/// How long a step runs before its starter moves workers that have not run: about a
/// scheduler slice (0.75 ms and more), within which a worker woken onto a busy core usually
/// gets it, and short beside a tick (4 ms). Measured on icl-livingroom-5 at 0.05 m on two
/// threads against no moves (BENCHMARKS.md, session 48): 1 ms took 0.83-0.92 of the time of a
/// frame with the release build and 0.94 with the installed (LTO) one; 0.15 and 0.5 ms helped
/// the first as much and made the second slower (1.06-1.12, moves made where the worker was
/// about to run, onto the core decoding the next frame), 2 ms helped either less.
pub const WAIT: Duration = Duration::from_millis(1);

/// The thread ids of the pool's workers by their index, as they recorded them.
static THREADS: Mutex<Vec<Option<sys::Tid>>> = Mutex::new(Vec::new());

/// Records the calling thread's id under its index in the current thread pool, for [`Step`]s
/// to move it (nothing outside a pool). Meant for a pool's `start_handler`.
pub fn register_thread() {
    if let Some(index) = rayon::current_thread_index() {
        record(index, sys::current());
    }
}

fn record(index: usize, tid: Option<sys::Tid>) {
    let mut threads = THREADS.lock().unwrap_or_else(|e| e.into_inner());
    if threads.len() <= index {
        threads.resize(index + 1, None);
    }
    threads[index] = tid;
}

/// One parallel step, watched from the thread that started it (see the module documentation).
pub struct Step {
    /// The starter's index in the pool; `None` when nothing is watched (one thread, outside a
    /// pool, or not Linux).
    starter: Option<usize>,
    start: Instant,
    /// Per worker index: whether it has run a job of this step, and whether it was moved.
    ran: Box<[AtomicBool]>,
    moved: Box<[AtomicBool]>,
    /// The workers' thread ids when the step started.
    threads: Vec<Option<sys::Tid>>,
}

impl Step {
    /// A step started by the calling thread.
    pub fn start() -> Step {
        let n = rayon::current_num_threads();
        let starter = rayon::current_thread_index().filter(|_| n > 1 && sys::SUPPORTED);
        if let Some(i) = starter {
            record(i, sys::current());
        }
        // (Nothing to watch: no flags, no ids.)
        let (watched, threads) = match starter {
            Some(_) => (n, THREADS.lock().unwrap_or_else(|e| e.into_inner()).iter().take(n).copied().collect()),
            None => (0, Vec::new()),
        };
        let flags = || (0..watched).map(|_| AtomicBool::new(false)).collect();
        Step { starter, start: Instant::now(), ran: flags(), moved: flags(), threads }
    }

    /// To be called at the start of each of the step's jobs, on the thread running it.
    #[inline]
    pub fn job(&self) {
        self.job_with(&sys::move_off_this_core);
    }

    /// [`Step::job`], moving workers with `mover(thread id)`.
    fn job_with(&self, mover: &dyn Fn(sys::Tid)) {
        let Some(starter) = self.starter else { return };
        let Some(me) = rayon::current_thread_index() else { return };
        if me != starter {
            if let Some(ran) = self.ran.get(me).filter(|r| !r.load(Relaxed)) {
                ran.store(true, Relaxed);
                // (First job of this step on this thread: it is known from now on.)
                if self.threads.get(me).is_none_or(Option::is_none) {
                    record(me, sys::current());
                }
            }
            return;
        }
        if self.start.elapsed() < WAIT {
            return;
        }
        for (w, tid) in self.threads.iter().enumerate() {
            let Some(tid) = tid else { continue };
            let waiting = w != me && self.ran.get(w).is_some_and(|r| !r.load(Relaxed));
            if waiting && !self.moved[w].swap(true, Relaxed) {
                mover(*tid);
            }
        }
    }
}

#[cfg(target_os = "linux")]
mod sys {
    use std::ffi::c_int;

    pub type Tid = c_int;
    pub const SUPPORTED: bool = true;

    /// glibc's and musl's `cpu_set_t`: 1,024 cores. (On a machine with more, the affinity
    /// calls fail and no worker is moved.)
    #[repr(C)]
    #[derive(Clone, Copy)]
    struct CpuSet([u64; 16]);

    unsafe extern "C" {
        fn gettid() -> Tid;
        fn sched_getcpu() -> c_int;
        fn sched_getaffinity(tid: Tid, size: usize, mask: *mut CpuSet) -> c_int;
        fn sched_setaffinity(tid: Tid, size: usize, mask: *const CpuSet) -> c_int;
        fn tgkill(tgid: Tid, tid: Tid, sig: c_int) -> c_int;
    }

    /// The calling thread's id.
    pub fn current() -> Option<Tid> {
        // SAFETY: `gettid` takes nothing and cannot fail.
        Some(unsafe { gettid() })
    }

    /// Moves thread `tid` of this process off the calling thread's core if it is queued
    /// there: its allowed cores narrowed to exclude that core (the kernel moves a queued
    /// thread at once), then restored as they were. Nothing if `tid` names no thread of this
    /// process (a recorded thread that has exited, its id perhaps reused elsewhere).
    pub fn move_off_this_core(tid: Tid) {
        let size = std::mem::size_of::<CpuSet>();
        let mut mask = CpuSet([0; 16]);
        if !ours(tid) {
            return;
        }
        // SAFETY: plain system calls; `mask` is a valid `cpu_set_t` of `size` bytes that
        // outlives them.
        unsafe {
            let cpu = sched_getcpu();
            if cpu < 0 || cpu as usize >= 1024 || sched_getaffinity(tid, size, &mut mask) != 0 {
                return;
            }
            let mut narrow = mask;
            narrow.0[cpu as usize / 64] &= !(1u64 << (cpu % 64));
            if narrow.0 == [0; 16] || narrow.0 == mask.0 {
                return; // nowhere else to go, or not allowed here anyway
            }
            if sched_setaffinity(tid, size, &narrow) == 0 {
                sched_setaffinity(tid, size, &mask);
            }
        }
    }

    /// Whether `tid` names a thread of this process.
    pub fn ours(tid: Tid) -> bool {
        // SAFETY: signal 0 sends nothing: it only checks that `tid` is in this process's
        // thread group.
        unsafe { tgkill(std::process::id() as Tid, tid, 0) == 0 }
    }

    #[cfg(test)]
    pub fn allowed(tid: Tid) -> [u64; 16] {
        let mut mask = CpuSet([0; 16]);
        // SAFETY: as in `move_off_this_core`.
        assert_eq!(unsafe { sched_getaffinity(tid, std::mem::size_of::<CpuSet>(), &mut mask) }, 0);
        mask.0
    }
}

#[cfg(not(target_os = "linux"))]
mod sys {
    pub type Tid = i32;
    pub const SUPPORTED: bool = false;
    pub fn current() -> Option<Tid> {
        None
    }
    pub fn move_off_this_core(_tid: Tid) {}
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex as StdMutex;

    /// In a pool of two, a worker that runs a job of the step is never moved; one that has
    /// not run by the time the step is [`WAIT`] old is moved once, by the starter only.
    #[test]
    fn only_workers_that_have_not_run_are_moved_once_by_the_starter() {
        if !sys::SUPPORTED {
            eprintln!("skipped: workers are watched on Linux only");
            return;
        }
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).start_handler(|_| register_thread()).build().unwrap();
        pool.install(|| {
            let moved = StdMutex::new(Vec::new());
            let mover = |tid| moved.lock().unwrap().push(tid);
            // The other worker runs a job (a join's second half, on the worker, is waited for).
            let step = Step::start();
            let me = rayon::current_thread_index().unwrap();
            rayon::broadcast(|c| {
                if c.index() != me {
                    step.job_with(&mover)
                }
            });
            std::thread::sleep(WAIT * 2);
            step.job_with(&mover);
            assert!(moved.lock().unwrap().is_empty(), "it ran");
            // A step whose only jobs run on the starter: the other is moved, once.
            let step = Step::start();
            step.job_with(&mover);
            // (Nothing is moved before the step is `WAIT` old, however this thread was delayed.)
            assert!(moved.lock().unwrap().is_empty() || step.start.elapsed() >= WAIT, "too soon");
            std::thread::sleep(WAIT * 2);
            step.job_with(&mover);
            step.job_with(&mover);
            let other = step.threads.iter().enumerate().find(|(i, t)| *i != me && t.is_some()).unwrap().1.unwrap();
            assert_eq!(*moved.lock().unwrap(), [other]);
            // Jobs on the other worker never move anyone.
            rayon::broadcast(|c| {
                if c.index() != me {
                    step.job_with(&|_| panic!("a worker moved a thread"))
                }
            });
        });
    }

    /// Moving a thread off this core leaves its allowed cores as they were; only this
    /// process's threads are moved (not an exited one's id, nor a child process's).
    #[cfg(target_os = "linux")]
    #[test]
    fn a_moved_thread_keeps_its_allowed_cores() {
        let me = sys::current().unwrap();
        let before = sys::allowed(me);
        sys::move_off_this_core(me);
        assert_eq!(sys::allowed(me), before);
        let exited = std::thread::spawn(sys::current).join().unwrap().unwrap();
        assert!(sys::ours(me) && !sys::ours(exited));
        let mut child = std::process::Command::new("sleep").arg("5").spawn().unwrap();
        assert!(!sys::ours(child.id() as sys::Tid));
        child.kill().unwrap();
        child.wait().unwrap();
    }
}
