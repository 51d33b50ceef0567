//! The small simulated scene several test files build maps from.

use mrfmap::frames::Frame;
use mrfmap::source::Scene;

/// A box on a floor seen from four sides by a small (80 x 60) camera.
const BOX_ON_FLOOR: &str = "[camera]\nfx = 60.0\nfy = 60.0\ncx = 39.5\ncy = 29.5\nwidth = 80\nheight = 60\n\
    depth_scale = 5000.0\n[noise]\nbias = [0.0]\nstd = [0.01]\n\
    [[box]]\nmin = [-3.0, -3.0, -0.2]\nmax = [3.0, 3.0, 0.0]\n\
    [[box]]\nmin = [-0.4, -0.3, 0.0]\nmax = [0.4, 0.3, 0.7]\n\
    [[view]]\neye = [2.0, 0.1, 1.0]\ntarget = [0.0, 0.0, 0.3]\n\
    [[view]]\neye = [-2.0, 0.2, 1.2]\ntarget = [0.0, 0.0, 0.3]\n\
    [[view]]\neye = [0.1, 2.0, 1.1]\ntarget = [0.0, 0.0, 0.3]\n\
    [[view]]\neye = [0.3, -2.0, 0.9]\ntarget = [0.0, 0.0, 0.3]\n";

/// The four noisy frames of the box on the floor (noise seeded by `seed`).
pub fn box_on_floor_frames(seed: u64) -> Vec<Frame> {
    let scene = Scene::from_toml(BOX_ON_FLOOR, "box-on-floor.toml".as_ref()).unwrap();
    scene.views.iter().enumerate().map(|(i, pose)| scene.frame(i, pose, Some(seed))).collect()
}
