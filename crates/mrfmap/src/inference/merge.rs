//! Merging two finished maps of one engine and resolution into one map holding both maps'
//! evidence (tiles built apart, a robot's sessions). How two voxels combine is the engine's
//! own rule, kept beside the engine:
//!
//! - **log-odds**: the exact sum of the two log-odds, clamped to the maps' clamping bounds,
//!   which is the map of all frames of both wherever neither half hit a clamp;
//! - **MRF**: the two marginals as independent evidence about the same prior,
//!   `logit p = logit p_a + logit p_b - logit prior`. Exact when the two maps saw disjoint
//!   parts of the world; where both saw a voxel it ignores the coupling that joint inference
//!   would find (rebuild from both keyframe sets for that);
//! - **CRM**: each voxel's distribution moment-matched to a Beta, and the two multiplied over
//!   the engine's uniform prior: `Beta(a_a + a_b - 1, b_a + b_b - 1)`. Exact for Beta
//!   posteriors of independent data; CRM's particle pdfs are close to Beta where the data are
//!   plentiful.
//!
//! A voxel only one map knows is copied from it.

use super::{EngineKind, crm, logodds, mrf};
use crate::error::{Error, Result};
use crate::map::{Map, MapVoxel};

/// Both maps' evidence in one map (see the module documentation for what that means per
/// engine). The maps must share engine and resolution.
///
/// ```
/// use mrfmap::map::EngineKind;
/// use mrfmap::inference::merge;
/// use mrfmap::map::{Map, MapVoxel, VoxelKey};
/// let mut a = Map::new(EngineKind::Mrf, 0.1).unwrap();
/// a.params.insert("prior".into(), "0.1".into());
/// let mut b = a.clone();
/// a.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.5, variance: 0.0 });
/// b.voxels.insert(VoxelKey([0, 0, 0]), MapVoxel { occupancy: 0.5, variance: 0.0 });
/// b.voxels.insert(VoxelKey([1, 0, 0]), MapVoxel { occupancy: 0.9, variance: 0.0 });
/// let m = merge(&a, &b).unwrap();
/// // Two maps each moving a voxel from the prior 0.1 to 0.5: together 0.9.
/// assert!((m.voxels.get(VoxelKey([0, 0, 0])).unwrap().occupancy - 0.9).abs() < 1e-6);
/// assert_eq!(m.voxels.get(VoxelKey([1, 0, 0])).unwrap().occupancy, 0.9);
/// ```
pub fn merge(a: &Map, b: &Map) -> Result<Map> {
    if a.engine != b.engine || a.resolution() != b.resolution() {
        return Err(Error::Invalid(format!(
            "can only merge maps of one engine and resolution: {} at {} m and {} at {} m",
            a.engine,
            a.resolution(),
            b.engine,
            b.resolution()
        )));
    }
    let combine: Box<dyn Fn(MapVoxel, MapVoxel) -> MapVoxel> = match a.engine {
        EngineKind::LogOdds => Box::new(logodds::merge_rule(recorded(a, "clamp_min")?, recorded(a, "clamp_max")?)),
        EngineKind::Mrf => Box::new(mrf::merge_rule(recorded(a, "prior")?)),
        EngineKind::Crm => Box::new(crm::merge_rule()),
    };
    let mut out = a.clone();
    for (key, vb) in b.voxels.iter() {
        let v = match a.voxels.get(key) {
            Some(va) => combine(*va, *vb),
            None => *vb,
        };
        out.voxels.insert(key, v);
    }
    out.params.insert("merged".into(), "true".into());
    Ok(out)
}

/// A number `map` records among its parameters, which merging needs.
fn recorded(map: &Map, name: &str) -> Result<f64> {
    let text = map.params.get(name).ok_or_else(|| {
        Error::Invalid(format!("the {} map does not record its {name}, which merging needs", map.engine))
    })?;
    text.parse().map_err(|_| Error::Invalid(format!("the map's {name} {text:?} is not a number")))
}
