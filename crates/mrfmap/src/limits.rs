//! Resource limits: how much memory one piece of work may take, checked against an estimate
//! before the work starts, so that a too-fine resolution or a huge image is a clear error
//! instead of an allocation failure minutes later.
//!
//! The limit is [`max_memory`]: what [`set_max_memory`] set (the CLI's `--max-memory`), else
//! the `MRFMAP_MAX_MEMORY` environment variable, else three quarters of the machine's
//! physical memory (`/proc/meminfo`; 8 GiB where that cannot be read).

use std::sync::atomic::{AtomicU64, Ordering};

use crate::error::{Error, Result};

static MAX_MEMORY: AtomicU64 = AtomicU64::new(0);

/// Sets the memory limit in bytes for this process (0: back to the default).
pub fn set_max_memory(bytes: u64) {
    MAX_MEMORY.store(bytes, Ordering::Relaxed);
}

/// The memory limit in bytes. An unreadable `MRFMAP_MAX_MEMORY` is ignored with a warning
/// (the command line refuses it: [`env_max_memory`]).
pub fn max_memory() -> u64 {
    match MAX_MEMORY.load(Ordering::Relaxed) {
        0 => env_max_memory()
            .unwrap_or_else(|e| {
                tracing::warn!("{e}; using the default limit");
                None
            })
            .unwrap_or_else(|| physical_memory().map_or(8 << 30, |m| m / 4 * 3)),
        set => set,
    }
}

/// The limit `MRFMAP_MAX_MEMORY` sets, if it is set: an error naming the variable and its
/// value when that is not a size (`8G`, `512M`, ...).
pub fn env_max_memory() -> Result<Option<u64>> {
    match std::env::var("MRFMAP_MAX_MEMORY") {
        Ok(v) => parse_bytes(&v)
            .map(Some)
            .map_err(|e| Error::Invalid(format!("MRFMAP_MAX_MEMORY={v:?} is not a memory size: {e}"))),
        Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(v)) => {
            Err(Error::Invalid(format!("MRFMAP_MAX_MEMORY={v:?} is not a memory size")))
        }
    }
}

/// Physical memory from `/proc/meminfo` (Linux), if readable.
pub fn physical_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// This process's resident memory from `/proc/self/status` (Linux), if readable: what a
/// stream of unknown length checks as it goes, where no estimate can be made up front.
///
/// ```
/// # #[cfg(target_os = "linux")]
/// assert!(mrfmap::limits::resident_memory().unwrap() > 0);
/// ```
pub fn resident_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Parses `8G`, `512M`, `1.5GiB`, `1000000` (bytes) and the like (K, M, G, T: powers of 1024).
///
/// ```
/// use mrfmap::limits::parse_bytes;
/// assert_eq!(parse_bytes("2G").unwrap(), 2 << 30);
/// assert_eq!(parse_bytes("1.5 GiB").unwrap(), 3 << 29);
/// assert!(parse_bytes("lots").is_err() && parse_bytes("0").is_err());
/// ```
pub fn parse_bytes(text: &str) -> Result<u64> {
    let t = text.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let scale: u64 = match unit.trim().trim_end_matches(['B', 'b']).trim_end_matches('i').to_ascii_uppercase().as_str()
    {
        "" => 1,
        "K" => 1 << 10,
        "M" => 1 << 20,
        "G" => 1 << 30,
        "T" => 1 << 40,
        _ => return Err(Error::Invalid(format!("memory size {text:?}: unknown unit (use K, M, G or T)"))),
    };
    match number.parse::<f64>() {
        Ok(v) if v > 0.0 && v.is_finite() && v * (scale as f64) < 1.8e19 => Ok((v * scale as f64) as u64),
        _ => Err(Error::Invalid(format!("memory size {text:?}: need a positive number such as 8G"))),
    }
}

/// `bytes` for people: `3.2 GiB`.
pub fn human(bytes: f64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"];
    let mut v = bytes;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < units.len() {
        v /= 1024.0;
        u += 1;
    }
    if u + 1 == units.len() && v >= 1024.0 { format!("{bytes:.1e} B") } else { format!("{v:.1} {}", units[u]) }
}

/// Refuses work whose memory `estimate` (bytes) is above [`max_memory`], saying what the work
/// is, the estimate, the limit, and `advice` on how to get under it.
pub fn check_memory(what: &str, estimate: f64, advice: &str) -> Result<()> {
    let limit = max_memory();
    if estimate > limit as f64 {
        return Err(Error::Memory(format!(
            "{what} would need about {} of memory, more than the limit of {} ({advice}; or raise the limit \
             with --max-memory / MRFMAP_MAX_MEMORY)",
            human(estimate),
            human(limit as f64)
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_and_messages() {
        assert!(physical_memory().is_none_or(|m| m > 1 << 20));
        assert_eq!(human(3.5 * (1u64 << 30) as f64), "3.5 GiB");
        assert_eq!(human(1e30), "1.0e30 B");
        set_max_memory(1 << 20);
        let e = check_memory("a map", 5e6, "use a coarser resolution").unwrap_err();
        // Its own kind, so that callers (Python: MemoryError) can tell it from bad input.
        assert!(matches!(e, Error::Memory(_)), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("4.8 MiB") && e.contains("1.0 MiB") && e.contains("coarser"), "{e}");
        assert!(check_memory("a map", 1e5, "").is_ok());
        set_max_memory(0);
        assert!(max_memory() >= 1 << 20);
    }
}
