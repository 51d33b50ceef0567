//! `mrfmap view`: a picture of a map (or a slice of it) as PNG, no viewer needed.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use mrfmap::map::Map;
use mrfmap::outputs::{Up, View, render_grid2d, render_map, slice_map};

#[derive(clap::Args)]
pub struct Args {
    /// Map file.
    map: PathBuf,
    /// Output PNG.
    #[arg(short, long)]
    output: PathBuf,
    /// Colour voxels by height, sigma (standard deviation of occupancy) or occupancy.
    #[arg(long, default_value = "height", value_parser = ["height", "sigma", "variance", "occupancy"])]
    color: String,
    /// Camera position X,Y,Z (default: above a corner of the map).
    #[arg(long, allow_hyphen_values = true)]
    eye: Option<String>,
    /// Point looked at X,Y,Z (default: the map's centre).
    #[arg(long, allow_hyphen_values = true)]
    target: Option<String>,
    /// Picture size WIDTHxHEIGHT.
    #[arg(long, default_value = "1024x768")]
    size: String,
    /// Horizontal field of view in degrees.
    #[arg(long, default_value_t = 60.0)]
    fov: f64,
    /// Draw voxels with occupancy above this.
    #[arg(long, default_value_t = 0.5, value_parser = super::threshold)]
    threshold: f32,
    /// The world direction drawn up and coloured as height: +z (ROS), or +y for worlds such as
    /// ICL-NUIM, 7-Scenes and Redwood whose gravity is along -y; -y, +x, -x, -z too. Default:
    /// what the map recorded from its dataset's world.toml, else +z.
    #[arg(long, allow_hyphen_values = true, value_parser = |s: &str| s.parse::<Up>().map_err(|e| e.to_string()))]
    up: Option<Up>,
    /// Instead of the 3D picture, the occupancy slice at AXIS=VALUE (e.g. z=0.5).
    #[arg(long, allow_hyphen_values = true)]
    slice: Option<String>,
}

fn triple(name: &str, text: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--{name} {text:?}: need X,Y,Z"))?;
    match v.as_slice() {
        &[x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => bail!("--{name} {text:?}: need three finite numbers X,Y,Z"),
    }
}

pub fn run(a: Args) -> Result<()> {
    super::options::check_output_folder(&a.output)?;
    let map = Map::load(&a.map)?;
    if map.voxels.is_empty() {
        bail!("{}: the map is empty: nothing to show", a.map.display());
    }
    let (lo, hi) = map.bounds().expect("map is not empty");
    let planar = hi[2] - lo[2] < 1.5 * map.resolution();
    let canvas = if planar && a.slice.is_none() && a.eye.is_none() && a.target.is_none() {
        // A one-layer map (a planar laser's): the grid itself, with its sigma.
        render_grid2d(&map.project(lo[2], hi[2])?, 1600)
    } else if let Some(slice) = &a.slice {
        let (axis, value) =
            slice.split_once('=').with_context(|| format!("--slice {slice:?}: need AXIS=VALUE, e.g. z=0.5"))?;
        let axis = match axis.trim() {
            "x" => 0,
            "y" => 1,
            "z" => 2,
            other => bail!("--slice: axis {other:?} is not x, y or z"),
        };
        let value: f64 = value.trim().parse().with_context(|| format!("--slice {slice:?}: bad value"))?;
        slice_map(&map, axis, value)?
    } else {
        let recorded = map.params.get("up").map(|u| u.parse::<Up>()).transpose()?;
        let mut view = View::overview(&map, a.up.or(recorded).unwrap_or(Up::Z)).expect("map is not empty");
        if let Some(e) = &a.eye {
            view.eye = triple("eye", e)?;
        }
        if let Some(t) = &a.target {
            view.target = triple("target", t)?;
        }
        let (w, h) = a.size.split_once('x').with_context(|| format!("--size {:?}: need WIDTHxHEIGHT", a.size))?;
        view.width = w.parse().with_context(|| format!("--size {:?}", a.size))?;
        view.height = h.parse().with_context(|| format!("--size {:?}", a.size))?;
        if view.width == 0 || view.height == 0 || view.width > 16384 || view.height > 16384 {
            bail!("--size {:?}: each side must be 1 to 16384 pixels", a.size);
        }
        view.fov_degrees = a.fov;
        view.threshold = a.threshold;
        view.colouring = a.color.parse()?;
        render_map(&map, &view)?
    };
    canvas.save(&a.output)?;
    println!("{}", a.output.display());
    Ok(())
}
