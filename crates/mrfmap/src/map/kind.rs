//! Which engine built a map. A finished [`Map`](super::Map) records its engine as a kind,
//! not a name, because what a map's numbers mean (and how two maps merge) depends on it; the
//! engines themselves live in [`crate::inference`], which re-exports this type.

use std::fmt;
use std::str::FromStr;

use crate::Choice;
use crate::error::{Error, Result};

/// The engines this build offers, and so the kinds of map there are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "&'static str")]
pub enum EngineKind {
    /// The log-odds occupancy grid (`inference::LogOddsEngine`): OctoMap's update.
    LogOdds,
    /// MRFMap's ray Markov random field (`inference::MrfEngine`).
    Mrf,
    /// Confidence-rich mapping (`inference::CrmEngine`): occupancy with a variance.
    Crm,
}

impl EngineKind {
    /// All engines, in the order the demo and reports use.
    pub const ALL: &[EngineKind] = &[EngineKind::LogOdds, EngineKind::Mrf, EngineKind::Crm];

    /// The name used on the command line, in Python and in map files.
    pub fn name(self) -> &'static str {
        match self {
            EngineKind::LogOdds => "logodds",
            EngineKind::Mrf => "mrf",
            EngineKind::Crm => "crm",
        }
    }
}

impl fmt::Display for EngineKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl Choice for EngineKind {
    const WHAT: &'static str = "engine";
    const ALL: &'static [Self] = EngineKind::ALL;

    fn name(self) -> &'static str {
        EngineKind::name(self)
    }
}

impl FromStr for EngineKind {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        <Self as Choice>::parse(s)
    }
}

impl TryFrom<String> for EngineKind {
    type Error = Error;

    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<EngineKind> for &'static str {
    fn from(kind: EngineKind) -> Self {
        kind.name()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinds_read_and_write_as_their_names() {
        #[derive(serde::Serialize, serde::Deserialize, PartialEq, Debug)]
        struct Header {
            engine: EngineKind,
        }
        for &kind in EngineKind::ALL {
            let text = toml::to_string(&Header { engine: kind }).unwrap();
            assert_eq!(text.trim(), format!("engine = \"{kind}\""));
            assert_eq!(toml::from_str::<Header>(&text).unwrap(), Header { engine: kind });
        }
        let e = toml::from_str::<Header>("engine = \"octomap\"").unwrap_err().to_string();
        assert!(e.contains("unknown engine \"octomap\"") && e.contains("logodds, mrf, crm"), "{e}");
    }
}
