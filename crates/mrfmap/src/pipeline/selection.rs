//! Which frames a build uses, and how a map records them: `--frames` / `--exclude` checked
//! against the source ([`select_frames`]), and the chosen indices as `0-5,7,9-11` in the map's
//! parameters ([`format_ranges`]), which `eval` reads back ([`parse_ranges`]) to tell
//! held-out views from the views a map was built from.

use crate::error::{Error, Result};

/// Checks that every index names a frame of a source with `len` frames.
pub fn check_indices(len: usize, indices: &[usize]) -> Result<()> {
    match indices.iter().find(|&&i| i >= len) {
        Some(i) => Err(Error::Invalid(format!(
            "frame index {i} is out of range: the dataset has {len} frames (0..{})",
            len.saturating_sub(1)
        ))),
        None => Ok(()),
    }
}

/// The frames to use: `frames` (or all when empty) minus `exclude`; indices must exist and
/// something must be left.
///
/// ```
/// use mrfmap::pipeline::select_frames;
/// assert_eq!(select_frames(5, &[], &[1, 3]).unwrap(), vec![0, 2, 4]);
/// assert!(select_frames(5, &[7], &[]).is_err());
/// assert!(select_frames(2, &[], &[0, 1]).is_err());
/// ```
pub fn select_frames(len: usize, frames: &[usize], exclude: &[usize]) -> Result<Vec<usize>> {
    check_indices(len, frames)?;
    check_indices(len, exclude)?;
    let chosen: Vec<usize> = if frames.is_empty() { (0..len).collect() } else { frames.to_vec() };
    let chosen: Vec<usize> = chosen.into_iter().filter(|i| !exclude.contains(i)).collect();
    if chosen.is_empty() {
        return Err(Error::Invalid("no frames left to integrate after --frames / --exclude".into()));
    }
    Ok(chosen)
}

/// `0-5,7,9-11` for the indices (sorted, each once).
///
/// ```
/// use mrfmap::pipeline::{format_ranges, parse_ranges};
/// assert_eq!(format_ranges(&[9, 0, 1, 2, 7, 10]), "0-2,7,9-10");
/// assert_eq!(parse_ranges("0-2,7,9-10"), vec![0, 1, 2, 7, 9, 10]);
/// ```
pub fn format_ranges(indices: &[usize]) -> String {
    let mut sorted = indices.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    let mut parts = Vec::new();
    let mut i = 0;
    while i < sorted.len() {
        let mut j = i;
        while j + 1 < sorted.len() && sorted[j + 1] == sorted[j] + 1 {
            j += 1;
        }
        parts.push(if i == j { sorted[i].to_string() } else { format!("{}-{}", sorted[i], sorted[j]) });
        i = j + 1;
    }
    parts.join(",")
}

/// The indices of [`format_ranges`]' text (malformed parts, and ranges of ten million or
/// more, are skipped: a map file's parameters are not trusted to size an allocation).
pub fn parse_ranges(text: &str) -> Vec<usize> {
    text.split(',')
        .flat_map(|part| match part.split_once('-') {
            Some((a, b)) => match (a.parse::<usize>(), b.parse::<usize>()) {
                (Ok(a), Ok(b)) if b >= a && b - a < 10_000_000 => (a..=b).collect(),
                _ => Vec::new(),
            },
            None => part.parse().ok().into_iter().collect(),
        })
        .collect()
}
