//! The map written as it is built, every so many seconds of recording time: map files into a
//! folder (each atomically, so a robot stack or viewer can pick them up) and, with the `mcap`
//! feature, a Foxglove timeline of them ([`crate::outputs::SceneTimeline`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::inference::Engine;

/// Writes the map as a build goes, every `every` seconds of the readings' stamps.
pub struct Snapshots {
    every: f64,
    dir: PathBuf,
    /// The recording time of the next snapshot (`None` before the first reading).
    next: Option<f64>,
    /// The time of the last reading integrated, and whether a snapshot holds it.
    last: Option<(f64, bool)>,
    written: usize,
    /// The timeline's path and, once the first snapshot is taken, its writer.
    #[cfg(feature = "mcap")]
    timeline: Option<(PathBuf, Option<crate::outputs::SceneTimeline>)>,
}

impl Snapshots {
    /// Snapshots every `every` seconds into the folder `dir` (made if missing). The first is
    /// taken after the first reading.
    pub fn new(every: f64, dir: &Path) -> Result<Self> {
        if !(every > 0.0 && every.is_finite()) {
            return Err(Error::Invalid(format!("snapshots: {every} is not a positive number of seconds")));
        }
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        Ok(Snapshots {
            every,
            dir: dir.to_path_buf(),
            next: None,
            last: None,
            written: 0,
            #[cfg(feature = "mcap")]
            timeline: None,
        })
    }

    /// Also writes the snapshots as a Foxglove timeline (MCAP) at `path`, put in place at
    /// [`Snapshots::finish`].
    #[cfg(feature = "mcap")]
    pub fn with_timeline(mut self, path: &Path) -> Self {
        self.timeline = Some((path.to_path_buf(), None));
        self
    }

    /// After a reading stamped `time` went into `engine`: a snapshot if one is due. Readings
    /// without a stamp (range scans) cannot be followed in time.
    pub fn after(&mut self, time: Option<f64>, engine: &dyn Engine) -> Result<()> {
        let Some(time) = time else {
            return Err(Error::Invalid("snapshots need readings with timestamps (depth frames)".into()));
        };
        let next = *self.next.get_or_insert(time);
        self.last = Some((time, false));
        if time >= next {
            self.next = Some(next + self.every * ((time - next) / self.every).floor() + self.every);
            self.write(time, engine)?;
        }
        Ok(())
    }

    fn write(&mut self, time: f64, engine: &dyn Engine) -> Result<()> {
        let params = BTreeMap::from([("snapshot_time".to_string(), format!("{time:.6}"))]);
        let path = self.dir.join(format!("{:05}_{time:.3}.mrfmap", self.written));
        self.save(time, engine, &path, params)?;
        self.written += 1;
        self.last = Some((time, true));
        Ok(())
    }

    /// Saves the snapshot at `path`. The timeline's diff of bricks needs the map: made once,
    /// saved and added. Without a timeline the snapshot is saved from the engine (a log-odds
    /// build then holds no finished map beside its grid).
    fn save(&mut self, time: f64, engine: &dyn Engine, path: &Path, params: BTreeMap<String, String>) -> Result<()> {
        #[cfg(feature = "mcap")]
        if let Some((file, timeline)) = &mut self.timeline {
            let mut map = engine.map();
            map.params.extend(params);
            map.save(path)?;
            if timeline.is_none() {
                *timeline = Some(crate::outputs::SceneTimeline::create(file, &map, Default::default())?);
            }
            return timeline.as_mut().expect("just made").add(&map, time).map(|_| ());
        }
        #[cfg(not(feature = "mcap"))]
        let _ = time; // (only the timeline stamps a snapshot with its time)
        engine.save_map(path, &params).map(|_| ())
    }

    /// After the last reading: its map too (if no snapshot holds it yet), and the timeline
    /// put in place. Returns the snapshots written.
    pub fn finish(mut self, engine: &dyn Engine) -> Result<usize> {
        if let Some((time, false)) = self.last {
            self.write(time, engine)?;
        }
        #[cfg(feature = "mcap")]
        if let Some((_, Some(timeline))) = self.timeline {
            timeline.finish()?;
        }
        Ok(self.written)
    }
}
