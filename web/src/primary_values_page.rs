//! The page's level-0 value reader (wasm32 only): where primary_values.rs's resident bricks come
//! from. A served store's bricks are fetched through its own asynchronous path (a third
//! [`BrickFetcher`] of served_store.rs, beside the slice views' and the oblique view's: the
//! same request, checksum and decoding path), at most [`PRIMARY_VALUE_REQUESTS`] asked for at
//! a time so a tool's bricks never crowd the views' off the page's few connections; the page's
//! sample is in memory already, copied in at most [`SAMPLE_BRICKS_PER_FRAME`] a frame.
//!
//! A tool runs over what is resident ([`PagePrimaryValues::intensity`]) and hands what it read
//! back ([`PagePrimaryValues::finish_run`]): complete, or the bricks it lacks, which are then
//! asked for; the tool runs again once one has arrived ([`PagePrimaryValues::take_arrived`]).
//! Nothing here waits: answers are taken when the frame comes.
//!
//! [`SAMPLE_BRICKS_PER_FRAME`]: crate::slice_views::SAMPLE_BRICKS_PER_FRAME

use std::rc::Rc;
use std::sync::Arc;

use strata_render::{BrickSource, BrickedVolume};
use strata_source::{BrickFetcher, FetchOptions, SourceError, VolumeSource};
use strata_types::{BrickId, ValueMapping};

use crate::primary_values::{
    resident_capacity_bricks, BricksRead, PrimaryValuesError, ResidentBricks, ResidentIntensity,
    PRIMARY_VALUES_CACHE_BYTES,
};
use crate::slice_views::SAMPLE_BRICKS_PER_FRAME;

/// Level-0 brick requests the value reader has out at once.
pub const PRIMARY_VALUE_REQUESTS: usize = 4;

/// Why the page cannot read a served store's values.
#[derive(Debug, thiserror::Error)]
pub enum PrimaryValuesPageError {
    #[error("reading the volume's values: {0}")]
    Fetcher(SourceError),
    #[error("the store has no asynchronous brick path")]
    NoAsynchronousPath,
}

/// Where the level-0 bricks come from.
enum Source {
    Served(Box<dyn BrickFetcher>),
    Sample(Rc<BrickedVolume>),
}

/// How a tool's run over the resident bricks went.
#[derive(Debug, PartialEq)]
pub enum RunVerdict {
    /// Every brick it read was resident: its answer stands.
    Complete,
    /// It lacked these many bricks (now asked for): run it again when one arrives.
    Waiting { missing: usize },
}

/// The primary's level-0 values for the page's segmentation tools.
pub struct PagePrimaryValues {
    source: Source,
    resident: ResidentBricks,
    mapping: ValueMapping,
    unit: String,
    dims: [u32; 3],
    /// The level-0 bricks the running tool lacks, most wanted first.
    wanted: Vec<[u32; 3]>,
    /// A brick arrived since the tool last ran.
    arrived: bool,
    /// A brick that could not be read (its request failed), shown by the tool.
    error: Option<String>,
}

impl PagePrimaryValues {
    /// The values of a served store, fetched through its asynchronous path.
    pub fn served(store: &dyn VolumeSource) -> Result<Self, PrimaryValuesPageError> {
        let fetcher = match store.start_fetching(FetchOptions {
            max_queued: PRIMARY_VALUE_REQUESTS + 1,
            max_in_transit: PRIMARY_VALUE_REQUESTS + 1,
            threads: 1,
        }) {
            Some(Ok(fetcher)) => fetcher,
            Some(Err(e)) => return Err(PrimaryValuesPageError::Fetcher(e)),
            None => return Err(PrimaryValuesPageError::NoAsynchronousPath),
        };
        let header = store.header();
        Ok(PagePrimaryValues::with_source(
            Source::Served(fetcher),
            header.value_mapping.mapping,
            header.value_mapping.unit.clone(),
            header.geometry.dims,
        ))
    }

    /// The values of the page's sample (in HU), from its in-memory bricks.
    pub fn sample(volume: Rc<BrickedVolume>) -> Self {
        let (mapping, dims) = (volume.mapping, volume.geometry.dims);
        PagePrimaryValues::with_source(Source::Sample(volume), mapping, "HU".into(), dims)
    }

    fn with_source(source: Source, mapping: ValueMapping, unit: String, dims: [u32; 3]) -> Self {
        PagePrimaryValues {
            source,
            resident: ResidentBricks::new(resident_capacity_bricks(PRIMARY_VALUES_CACHE_BYTES)),
            mapping,
            unit,
            dims,
            wanted: Vec::new(),
            arrived: false,
            error: None,
        }
    }

    /// The tools' view of the resident bricks, for one run.
    pub fn intensity(&self) -> ResidentIntensity<'_> {
        ResidentIntensity::new(&self.resident, self.mapping, &self.unit, self.dims)
    }

    /// Takes a run's reads: the bricks it used are kept longest; the ones it lacked are asked
    /// for. An error when the run needs more bricks at once than the page keeps.
    pub fn finish_run(&mut self, read: BricksRead) -> Result<RunVerdict, PrimaryValuesError> {
        self.resident.touch(&read.used);
        read.check(self.resident.capacity())?;
        self.arrived = false;
        let missing = read.missing.len();
        self.wanted = read.missing;
        Ok(if missing == 0 {
            RunVerdict::Complete
        } else {
            RunVerdict::Waiting { missing }
        })
    }

    /// Whether a wanted brick arrived since the last run (the tool's cue to run again).
    pub fn take_arrived(&mut self) -> bool {
        std::mem::take(&mut self.arrived)
    }

    /// Asks for those of `bricks` that are not resident (beside what the running job wants);
    /// returns how many that is.
    pub fn want(&mut self, bricks: &[[u32; 3]]) -> usize {
        let mut missing = 0;
        for coords in bricks {
            if self.resident.contains(*coords) {
                continue;
            }
            missing += 1;
            if !self.wanted.contains(coords) {
                self.wanted.push(*coords);
            }
        }
        missing
    }

    /// Marks the bricks a run read as just used (a run that met no missing brick by
    /// construction: [`Self::want`] was asked first).
    pub fn touch(&mut self, read: &BricksRead) {
        self.resident.touch(&read.used);
    }

    /// Stops asking for the bricks of a tool that was cancelled or finished.
    pub fn forget_wanted(&mut self) {
        self.wanted.clear();
        self.arrived = false;
    }

    /// Wanted bricks not resident yet.
    pub fn still_missing(&self) -> usize {
        self.wanted
            .iter()
            .filter(|c| !self.resident.contains(**c))
            .count()
    }

    /// A brick that failed to arrive, once.
    pub fn take_error(&mut self) -> Option<String> {
        self.error.take()
    }

    /// Takes the bricks that arrived and asks for the wanted ones not resident yet. Call once
    /// a frame.
    pub fn pump(&mut self, ctx: &egui::Context) {
        let missing: Vec<[u32; 3]> = self
            .wanted
            .iter()
            .copied()
            .filter(|c| !self.resident.contains(*c))
            .collect();
        match &mut self.source {
            Source::Served(fetcher) => {
                for result in fetcher.try_results() {
                    match result.outcome {
                        Ok(voxels) if result.id.level == 0 => {
                            self.resident.insert(result.id.coords, voxels);
                            self.arrived = true;
                        }
                        Ok(_) => {}
                        Err(e) => self.error = Some(e.to_string()),
                    }
                    fetcher.complete(result.id);
                }
                let demand: Vec<(BrickId, f64)> = missing
                    .iter()
                    .take(PRIMARY_VALUE_REQUESTS)
                    .enumerate()
                    .map(|(rank, c)| (BrickId::new(0, *c), (PRIMARY_VALUE_REQUESTS - rank) as f64))
                    .collect();
                fetcher.set_requests(&demand, &[]);
                if !demand.is_empty() {
                    // Answers arrive between frames and wake nothing: poll until they are in.
                    ctx.request_repaint();
                }
            }
            Source::Sample(volume) => {
                for coords in missing.into_iter().take(SAMPLE_BRICKS_PER_FRAME) {
                    match volume.brick(0, coords) {
                        Some(payload) => {
                            self.resident.insert(coords, Arc::new(payload.to_vec()));
                            self.arrived = true;
                        }
                        None => {
                            self.error =
                                Some(format!("the sample has no level-0 brick at {coords:?}"));
                        }
                    }
                }
                if self.arrived {
                    ctx.request_repaint();
                }
            }
        }
    }
}
