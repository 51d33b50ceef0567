//! `mrfmap query`: what a planner asks of a map — points, segments, polylines and boxes, with
//! confidence — as text or one JSON object (the contract scripts rely on: README "Queries").

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use mrfmap::map::Aabb;
use mrfmap::map::{Map, TiledMap};
use mrfmap::outputs::{
    BoxAnswer, LazyTiles, PointAnswer, QueryOptions, SegmentAnswer, VoxelSource, check_path, query_box, query_points,
    query_polyline, query_segments,
};
use serde_json::{Value, json};

#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("what").required(true).multiple(true).args(["segment", "polyline", "points", "boxes"]))]
pub struct Args {
    /// Map file written by `mrfmap build`, or a tiled map's folder (only the tiles the queries
    /// reach are read).
    map: PathBuf,
    /// A straight path `X,Y,Z:X,Y,Z` (metres, world frame); repeat for more.
    #[arg(long, value_name = "X,Y,Z:X,Y,Z", allow_hyphen_values = true)]
    segment: Vec<String>,
    /// A path through waypoints `X,Y,Z:X,Y,Z:...` (each voxel counted once); repeat for more.
    #[arg(long, value_name = "X,Y,Z:X,Y,Z:...", allow_hyphen_values = true)]
    polyline: Vec<String>,
    /// A CSV file of points `x,y,z`, one per line (`#` comments and a header line allowed).
    #[arg(long, value_name = "FILE.csv")]
    points: Option<PathBuf>,
    /// An axis-aligned box `XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX`; repeat for more.
    #[arg(long = "box", id = "boxes", value_name = "XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX", allow_hyphen_values = true)]
    boxes: Vec<String>,
    /// Occupancy assumed where the map knows nothing.
    #[arg(long, default_value_t = 0.5)]
    unknown: f64,
    /// Standard deviations added per voxel for the confidence bound `p_free_lcb`.
    #[arg(long, default_value_t = 2.0)]
    k: f64,
    /// Occupancy above which a voxel is occupied (`first_hit`, box counts).
    #[arg(long, default_value_t = 0.5)]
    threshold: f64,
    /// Print one JSON object `{"segments": [...], "polylines": [...], "points": [...], "boxes": [...]}`.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let options = QueryOptions { unknown: a.unknown, k: a.k, threshold: a.threshold };
    options.validate()?;
    let segments: Vec<([f64; 3], [f64; 3])> = a.segment.iter().map(|s| parse_segment(s)).collect::<Result<_>>()?;
    let polylines: Vec<Vec<[f64; 3]>> = a.polyline.iter().map(|s| parse_polyline(s)).collect::<Result<_>>()?;
    let boxes: Vec<Aabb> =
        a.boxes.iter().map(|b| Aabb::parse(b).with_context(|| format!("--box {b}"))).collect::<Result<_>>()?;
    let points = match &a.points {
        Some(path) => read_points(path)?,
        None => Vec::new(),
    };
    let check_paths = |r: f64| -> Result<()> {
        for ((from, to), text) in segments.iter().zip(&a.segment) {
            check_path(&[*from, *to], r).with_context(|| format!("--segment {text}"))?;
        }
        for (points, text) in polylines.iter().zip(&a.polyline) {
            check_path(points, r).with_context(|| format!("--polyline {text}"))?;
        }
        Ok(())
    };
    let (seg_answers, poly_answers, point_answers, box_answers) = if TiledMap::is_tiled(&a.map) {
        // A tiled map is read lazily: only the tiles the queries reach are opened.
        let tiled = TiledMap::open(&a.map)?;
        check_paths(tiled.index().resolution)?;
        let lazy = LazyTiles::new(&tiled);
        let answers = answer_all(&lazy, &segments, &polylines, &points, &boxes, &options)?;
        let opened = lazy.finish()?;
        tracing::info!("{}: read {opened} of {} tiles", a.map.display(), tiled.index().tiles.len());
        answers
    } else {
        let map = Map::load(&a.map)?;
        check_paths(map.resolution())?;
        answer_all(&map, &segments, &polylines, &points, &boxes, &options)?
    };

    if a.json {
        let path = |s: &SegmentAnswer| {
            json!({
                "p_free": s.p_free, "expected_occupied": s.expected_occupied, "p_free_lcb": s.p_free_lcb,
                "first_hit": s.first_hit, "voxels": s.voxels, "unknown": s.unknown,
            })
        };
        let with = |mut v: Value, key: &str, value: Value| {
            v[key] = value;
            v
        };
        let out = json!({
            "segments": segments.iter().zip(&seg_answers)
                .map(|((from, to), s)| with(with(path(s), "from", json!(from)), "to", json!(to)))
                .collect::<Vec<Value>>(),
            "polylines": polylines.iter().zip(&poly_answers)
                .map(|(points, s)| with(path(s), "points", json!(points)))
                .collect::<Vec<Value>>(),
            "points": points.iter().zip(&point_answers).map(|(p, q)| json!({
                "point": p, "occupancy": q.occupancy, "std": q.sigma, "known": q.known,
            })).collect::<Vec<Value>>(),
            "boxes": boxes.iter().zip(&box_answers).map(|(b, q)| json!({
                "min": b.min, "max": b.max, "max_occupancy": q.max_occupancy, "p_free": q.p_free,
                "occupied": q.occupied, "free": q.free, "unknown": q.unknown,
            })).collect::<Vec<Value>>(),
        });
        println!("{out}");
        return Ok(());
    }
    let fmt3 = |p: &[f64; 3]| format!("{:.3},{:.3},{:.3}", p[0], p[1], p[2]);
    let describe = |s: &SegmentAnswer| {
        let hit = s.first_hit.as_ref().map_or("none".into(), fmt3);
        format!(
            "p_free {:.4} (k = {} bound {:.4}), expected occupied {:.3}, {} voxels ({} unknown), first hit {hit}",
            s.p_free, a.k, s.p_free_lcb, s.expected_occupied, s.voxels, s.unknown
        )
    };
    for ((from, to), s) in segments.iter().zip(&seg_answers) {
        println!("segment {} -> {}: {}", fmt3(from), fmt3(to), describe(s));
    }
    for (points, s) in polylines.iter().zip(&poly_answers) {
        let path: Vec<String> = points.iter().map(fmt3).collect();
        println!("polyline {}: {}", path.join(" -> "), describe(s));
    }
    for (p, q) in points.iter().zip(&point_answers) {
        let known = if q.known { "" } else { " (unknown)" };
        println!("point {}: occupancy {:.4} +- {:.4}{known}", fmt3(p), q.occupancy, q.sigma);
    }
    for (b, q) in boxes.iter().zip(&box_answers) {
        println!(
            "box {} to {}: max occupancy {:.4}, p_free {:.4}, {} occupied, {} free, {} unknown",
            fmt3(&b.min),
            fmt3(&b.max),
            q.max_occupancy,
            q.p_free,
            q.occupied,
            q.free,
            q.unknown
        );
    }
    Ok(())
}

/// Every query's answers from `source`.
#[allow(clippy::type_complexity)]
fn answer_all(
    source: &impl VoxelSource,
    segments: &[([f64; 3], [f64; 3])],
    polylines: &[Vec<[f64; 3]>],
    points: &[[f64; 3]],
    boxes: &[Aabb],
    options: &QueryOptions,
) -> Result<(Vec<SegmentAnswer>, Vec<SegmentAnswer>, Vec<PointAnswer>, Vec<BoxAnswer>)> {
    Ok((
        query_segments(source, segments, options),
        polylines.iter().map(|p| query_polyline(source, p, options)).collect(),
        query_points(source, points, options),
        boxes.iter().map(|b| query_box(source, b, options)).collect::<Result<_, _>>()?,
    ))
}

fn parse_point(text: &str) -> Option<[f64; 3]> {
    let v: Vec<f64> = text.split(',').map(|s| s.trim().parse::<f64>()).collect::<Result<_, _>>().ok()?;
    let p: [f64; 3] = v.try_into().ok()?;
    p.iter().all(|x| x.is_finite()).then_some(p)
}

fn parse_segment(text: &str) -> Result<([f64; 3], [f64; 3])> {
    match parse_points(text).as_deref() {
        Some([a, b]) => Ok((*a, *b)),
        _ => bail!("--segment {text:?}: need X,Y,Z:X,Y,Z with finite numbers"),
    }
}

fn parse_polyline(text: &str) -> Result<Vec<[f64; 3]>> {
    parse_points(text)
        .filter(|p| p.len() >= 2)
        .with_context(|| format!("--polyline {text:?}: need X,Y,Z:X,Y,Z[:X,Y,Z...] with finite numbers"))
}

/// `X,Y,Z:X,Y,Z:...`
fn parse_points(text: &str) -> Option<Vec<[f64; 3]>> {
    text.split(':').map(parse_point).collect()
}

/// Points of a CSV file: `x,y,z` per line; blank lines and `#` comments skipped, and a first
/// line that is not numbers taken as a header.
fn read_points(path: &Path) -> Result<Vec<[f64; 3]>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}", path.display()))?;
    let mut points = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        match parse_point(line) {
            Some(p) => points.push(p),
            None if i == 0 => {} // a header
            None => bail!("{}:{}: need x,y,z (three finite numbers), got {line:?}", path.display(), i + 1),
        }
    }
    Ok(points)
}
