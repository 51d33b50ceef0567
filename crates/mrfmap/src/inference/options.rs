//! What a user sets for a build, whichever engine runs it: [`BuildOptions`]. The command
//! line's flags and Python's keyword arguments both fill one, and [`BuildOptions::config`] is
//! the one place that turns it into an [`EngineConfig`], with the rules that tie options
//! together (how `iterations` reads with and without `tolerance`) and the checks that need no
//! engine (ray limits, clamping bounds). Each engine checks its own parameters when it is
//! made ([`super::new_engine`]).

use super::{
    Allocation, CrmParams, DEFAULT_MAX_SWEEPS, EngineConfig, EngineKind, KeyframeSelection, LogOddsParams, Marking,
    MrfParams,
};
use crate::error::{Error, Result};
use crate::map::Aabb;
use crate::rays::RayLimits;

/// A build's options; [`Default`] gives every engine's defaults.
///
/// ```
/// use mrfmap::inference::{BuildOptions, EngineKind};
/// let o = BuildOptions { tolerance: Some(1e-3), ..BuildOptions::default() };
/// let config = o.config(EngineKind::Mrf, 0.05).unwrap();
/// // With a tolerance, `iterations` is a cap on the sweeps, 10 unless given.
/// assert_eq!((config.mrf.iterations, config.mrf.tolerance), (10, Some(1e-3)));
/// assert!(BuildOptions { clamp: Some((0.9, 0.2)), ..o }.config(EngineKind::LogOdds, 0.05).is_err());
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildOptions {
    /// Readings are cut at this range (metres) and then mark free space only.
    pub max_range: Option<f64>,
    /// Only this box is mapped.
    pub bounds: Option<Aabb>,
    /// MRF: sweeps of belief propagation. Alone: exactly this many full sweeps (default
    /// [`super::DEFAULT_SWEEPS`]); with `tolerance`: at most this many (default
    /// [`DEFAULT_MAX_SWEEPS`]).
    pub iterations: Option<usize>,
    /// MRF: change-driven belief propagation until no marginal moves by more than this
    /// ([`MrfParams::tolerance`]).
    pub tolerance: Option<f64>,
    /// MRF: the online schedule's order for a batch build, this many sweeps' worth of tile
    /// traces at most ([`MrfParams::work`]).
    pub work: Option<f64>,
    /// MRF: prior occupancy of every voxel.
    pub prior: f64,
    /// MRF: where bricks are allocated.
    pub allocation: Allocation,
    /// MRF: which frames become keyframes.
    pub keyframes: KeyframeSelection,
    /// MRF: share of a tile's old message kept when it is replaced ([`MrfParams::damping`]).
    pub damping: f64,
    /// MRF: ray spacing in voxel edges ([`MrfParams::ray_spacing`]).
    pub ray_spacing: f64,
    /// MRF: evidence below which a voxel is unknown ([`MrfParams::min_evidence`]).
    pub min_evidence: f64,
    /// CRM: particles per voxel pdf.
    pub particles: usize,
    /// Log-odds: how a depth image's crossed voxels are found.
    pub marking: Marking,
    /// Log-odds: clamping thresholds as probabilities `(min, max)` (default: OctoMap's).
    pub clamp: Option<(f64, f64)>,
}

impl Default for BuildOptions {
    fn default() -> Self {
        let mrf = MrfParams::default();
        BuildOptions {
            max_range: None,
            bounds: None,
            iterations: None,
            tolerance: None,
            work: None,
            prior: mrf.prior,
            allocation: mrf.allocation,
            keyframes: mrf.keyframes,
            damping: mrf.damping,
            ray_spacing: mrf.ray_spacing,
            min_evidence: mrf.min_evidence,
            particles: CrmParams::default().particles,
            marking: LogOddsParams::default().marking,
            clamp: None,
        }
    }
}

impl BuildOptions {
    /// The configuration of engine `kind` at `resolution` these options describe; an error
    /// for limits or clamping bounds that no engine could use.
    pub fn config(&self, kind: EngineKind, resolution: f64) -> Result<EngineConfig> {
        let limits = RayLimits { max_range: self.max_range, bounds: self.bounds };
        limits.validate()?;
        let d = LogOddsParams::default();
        let (clamp_min, clamp_max) = self.clamp.unwrap_or((d.clamp_min, d.clamp_max));
        if !(clamp_min > 0.0 && clamp_min < clamp_max && clamp_max < 1.0) {
            return Err(Error::Invalid(format!(
                "clamping bounds (clamp) need 0 < MIN < MAX < 1, got {clamp_min}, {clamp_max}"
            )));
        }
        let (iterations, tolerance) = match self.tolerance {
            Some(t) => (self.iterations.unwrap_or(DEFAULT_MAX_SWEEPS), Some(t)),
            None => (self.iterations.unwrap_or(MrfParams::default().iterations), None),
        };
        if iterations == 0 {
            return Err(Error::Invalid("MRF iterations must be at least 1".into()));
        }
        if self.particles < 2 {
            return Err(Error::Invalid(format!("CRM needs at least 2 particles, got {}", self.particles)));
        }
        Ok(EngineConfig {
            kind,
            resolution,
            limits,
            logodds: LogOddsParams { marking: self.marking, clamp_min, clamp_max, ..d },
            mrf: MrfParams {
                prior: self.prior,
                iterations,
                allocation: self.allocation,
                keyframes: self.keyframes,
                damping: self.damping,
                ray_spacing: self.ray_spacing,
                tolerance,
                work: self.work,
                min_evidence: self.min_evidence,
            },
            crm: CrmParams { particles: self.particles },
            camera: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_engines_defaults() {
        for &kind in EngineKind::ALL {
            assert_eq!(BuildOptions::default().config(kind, 0.05).unwrap(), EngineConfig::new(kind, 0.05));
        }
    }

    #[test]
    fn iterations_read_with_and_without_tolerance() {
        let alone = BuildOptions { iterations: Some(7), ..Default::default() }.config(EngineKind::Mrf, 0.1).unwrap();
        assert_eq!((alone.mrf.iterations, alone.mrf.tolerance), (7, None));
        let capped = BuildOptions { iterations: Some(4), tolerance: Some(0.01), ..Default::default() };
        let capped = capped.config(EngineKind::Mrf, 0.1).unwrap();
        assert_eq!((capped.mrf.iterations, capped.mrf.tolerance), (4, Some(0.01)));
    }

    #[test]
    fn options_no_engine_could_use_are_refused() {
        let bad = [
            BuildOptions { max_range: Some(-1.0), ..Default::default() },
            BuildOptions { clamp: Some((0.0, 0.5)), ..Default::default() },
            BuildOptions { clamp: Some((0.6, 0.5)), ..Default::default() },
            BuildOptions { iterations: Some(0), ..Default::default() },
            BuildOptions { particles: 1, ..Default::default() },
        ];
        for o in bad {
            assert!(o.config(EngineKind::LogOdds, 0.05).is_err(), "{o:?}");
        }
    }
}
