//! How good a map is. `accuracy`: the MRFMap paper's accuracy metric on held-out views (a
//! map's rays against a depth image it was not built from). `truth`: against an analytic
//! scene's true occupancy (or a reference from noise-free depth), the CRM paper's MAE, ROC
//! AUC, inconsistency and sigma-error correlation.

mod accuracy;
mod truth;

pub use accuracy::{
    AccuracyParams, PeakRule, PixelClass, ProfileStep, RayVerdict, Scorer, VISIBILITY_FLOOR, ViewScore, score_view,
};
pub use truth::{
    TruthMetrics, VoxelTruth, grid_world_truths, mean_sigma, metrics_of, pearson, roc_auc, surface_truth,
    true_occupancy, truth_metrics, voxel_truths,
};
