//! The block oracle (block_oracle.rs) built a bounded number of slots at a time, for a thread
//! that must not stop for the whole build: the browser page has one thread, and a frame that
//! spent 0.1-1 s on every resident node's voxels would freeze it. The build has the one-shot
//! `block_oracle_with`'s two phases, each slot by slot: the own distances of every used slot
//! (its node's voxels), then, once all of them are known, the dilation of every used slot
//! (which reads its neighbours' own distances across node faces). Each [`BlockOracleBuild::step`]
//! does at most the slots it is given; the table it finishes with is the one-shot's, value for
//! value (`an_oracle_built_a_few_slots_at_a_time_equals_the_one_shot_oracle`).
//!
//! A build belongs to the page table and knobs it was made with; the caller keeps it with its
//! key and drops it when the cut or the transfer function changes (the viewers' `OracleKey`).
//! A node whose payload the source does not hold counts as transparent, as in the one-shot
//! build; [`BlockOracleBuild::missing_bricks`] says how many there were, so a caller can refuse
//! a table that assumed so.

use std::sync::Arc;

use crate::model::layout::BrickSource;
use crate::model::page_table::PageTable;
use crate::model::transfer_function::TransferFunction;

use super::block_oracle::{nodes_of_slots, slot_blocks_mut, DistanceRule, BLOCKS_PER_SLOT};
use super::oracle::OracleTarget;

/// An oracle being built; [`BlockOracleBuild::step`] until [`BlockOracleBuild::finished`].
pub struct BlockOracleBuild {
    table: Arc<PageTable>,
    transfer_function: TransferFunction,
    rule: DistanceRule,
    node_of_slot: Vec<Option<(u8, [u32; 3])>>,
    own: Vec<f64>,
    dilated: Vec<f64>,
    phase: Phase,
    /// Used slots done, over both phases.
    slots_done: usize,
    used_slots: usize,
    missing_bricks: usize,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    /// Own distances, from this slot on.
    Own(usize),
    /// Dilation, from this slot on.
    Dilate(usize),
    Done,
}

impl BlockOracleBuild {
    /// A build of `block_oracle_with(table, _, mapping, transfer_function, epsilon, l_max,
    /// quality, target)`; nothing is computed yet.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        table: Arc<PageTable>,
        mapping: strata_types::ValueMapping,
        transfer_function: &TransferFunction,
        epsilon: f64,
        l_max: u32,
        quality: f64,
        target: OracleTarget,
    ) -> Self {
        let rule = DistanceRule::new(mapping, epsilon, l_max, quality, target);
        let node_of_slot = nodes_of_slots(&table);
        let used_slots = node_of_slot.iter().filter(|n| n.is_some()).count();
        let own = vec![rule.coarsest; node_of_slot.len() * BLOCKS_PER_SLOT];
        BlockOracleBuild {
            table,
            transfer_function: transfer_function.clone(),
            rule,
            dilated: own.clone(),
            own,
            node_of_slot,
            phase: Phase::Own(0),
            slots_done: 0,
            used_slots,
            missing_bricks: 0,
        }
    }

    /// The page table the oracle is built for.
    pub fn table(&self) -> &Arc<PageTable> {
        &self.table
    }

    /// Does at most `most_slots` used slots' work (at least one), reading node payloads from
    /// `source`. True once the table is complete.
    pub fn step<S: BrickSource + ?Sized>(&mut self, source: &S, most_slots: usize) -> bool {
        self.skip_unused_slots();
        for _ in 0..most_slots.max(1) {
            match self.phase {
                Phase::Own(slot) => {
                    if let Some(&Some((level, node))) = self.node_of_slot.get(slot) {
                        match source.brick(level, node) {
                            Some(brick) => self.rule.own_distances(
                                &self.transfer_function,
                                level,
                                brick,
                                slot_blocks_mut(&mut self.own, slot),
                            ),
                            None => self.missing_bricks += 1,
                        }
                        self.slots_done += 1;
                    }
                    self.phase = Phase::Own(slot + 1);
                }
                Phase::Dilate(slot) => {
                    if let Some(&Some((level, node))) = self.node_of_slot.get(slot) {
                        self.rule.dilate(
                            &self.table,
                            &self.own,
                            slot,
                            level,
                            node,
                            slot_blocks_mut(&mut self.dilated, slot),
                        );
                        self.slots_done += 1;
                    }
                    self.phase = Phase::Dilate(slot + 1);
                }
                Phase::Done => break,
            }
            // So that a step which did the last used slot reports the table complete.
            self.skip_unused_slots();
        }
        self.phase == Phase::Done
    }

    /// Moves past the slots no node uses and the end of a phase (no work in either).
    fn skip_unused_slots(&mut self) {
        let slots = self.node_of_slot.len();
        let unused = |slot: usize| self.node_of_slot.get(slot).is_some_and(Option::is_none);
        loop {
            self.phase = match self.phase {
                Phase::Own(slot) if slot >= slots => Phase::Dilate(0),
                Phase::Own(slot) if unused(slot) => Phase::Own(slot + 1),
                Phase::Dilate(slot) if slot >= slots => Phase::Done,
                Phase::Dilate(slot) if unused(slot) => Phase::Dilate(slot + 1),
                _ => return,
            };
        }
    }

    /// Used slots done and to do, over both phases (each used slot counts twice).
    pub fn progress(&self) -> (usize, usize) {
        (self.slots_done, 2 * self.used_slots)
    }

    /// Nodes whose payload the source did not hold (taken as transparent).
    pub fn missing_bricks(&self) -> usize {
        self.missing_bricks
    }

    /// The finished table (`block_oracle_with`'s), or None while steps remain.
    pub fn finished(&self) -> Option<Vec<f32>> {
        (self.phase == Phase::Done).then(|| self.dilated.iter().map(|&d| d as f32).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::layout::{BRICK_APRON, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};
    use crate::model::page_table::PageEntry;
    use crate::passes::adaptive::block_oracle_with;
    use std::collections::HashMap;

    /// Nodes of levels 0 and 1 with structure (a sphere's shell of values, different per
    /// node) in a sparse table with unused slots between the used ones.
    struct Payloads(HashMap<(u8, [u32; 3]), Vec<u16>>);

    impl BrickSource for Payloads {
        fn brick(&self, level: u8, node: [u32; 3]) -> Option<&[u16]> {
            self.0.get(&(level, node)).map(Vec::as_slice)
        }
    }

    fn shell(seed: u32) -> Vec<u16> {
        let p = BRICK_PAYLOAD as i64;
        let mut voxels = vec![0u16; BRICK_PAYLOAD_VOXELS];
        let centre = BRICK_APRON as i64 + 4 + (seed as i64 * 7) % 20;
        for z in 0..p {
            for y in 0..p {
                for x in 0..p {
                    let r2 = (x - centre).pow(2) + (y - 16).pow(2) + (z - 12).pow(2);
                    if (60..200).contains(&r2) {
                        voxels[(x + p * (y + p * z)) as usize] = 150 + (r2 % 60) as u16;
                    }
                }
            }
        }
        voxels
    }

    /// A 4×2×2 page grid: the left half at level 1 (one node over 2³ cells), the right half's
    /// cells at level 0; slots spread out, one node missing from the source.
    fn mixed_cut() -> (PageTable, Payloads) {
        let mut table = PageTable::new([4, 2, 2]);
        let mut payloads = HashMap::new();
        for z in 0..2u32 {
            for y in 0..2u32 {
                for x in 0..2u32 {
                    let i = table.linear([x, y, z]);
                    table.entries[i] = PageEntry::resident(9, 1);
                }
                for x in 2..4u32 {
                    let i = table.linear([x, y, z]);
                    let slot = 2 * (x + 2 * (y + 2 * z));
                    table.entries[i] = PageEntry::resident(slot, 0);
                    if [x, y, z] != [3, 1, 1] {
                        payloads.insert((0, [x, y, z]), shell(slot));
                    }
                }
            }
        }
        payloads.insert((1, [0, 0, 0]), shell(3));
        (table, Payloads(payloads))
    }

    #[test]
    fn an_oracle_built_a_few_slots_at_a_time_equals_the_one_shot_oracle() {
        let (table, source) = mixed_cut();
        let table = Arc::new(table);
        let tf = TransferFunction::new(
            "shell",
            &[(0.0, 0.0), (140.0, 0.0), (180.0, 0.6), (1000.0, 0.9)],
            &[(0.0, [1.0, 0.2, 0.1]), (200.0, [1.0; 3])],
        );
        let mapping = strata_types::ValueMapping::default();
        for (target, quality, epsilon) in [
            (OracleTarget::Opacity, 1.0, 0.001),
            (OracleTarget::Opacity, 0.5, 0.02),
            (OracleTarget::LitColour { shadowed: true }, 2.0, 0.001),
        ] {
            let one_shot =
                block_oracle_with(&table, &source, mapping, &tf, epsilon, 3, quality, target);
            // Not trivial: fine and coarse distances both occur.
            assert!(one_shot.contains(&1.0) && one_shot.iter().any(|&d| d >= 4.0));
            for most_slots in [1, 3, 100] {
                let mut build =
                    BlockOracleBuild::new(table.clone(), mapping, &tf, epsilon, 3, quality, target);
                let mut steps = 0;
                while !build.step(&source, most_slots) {
                    assert!(build.finished().is_none());
                    steps += 1;
                    assert!(steps < 1000, "the build never finishes");
                }
                // 9 used slots, each done twice: the number of steps follows from the bound.
                assert_eq!(build.progress(), (18, 18));
                assert_eq!(steps + 1, 18_usize.div_ceil(most_slots), "{most_slots}");
                assert_eq!(build.missing_bricks(), 1);
                assert_eq!(
                    build.finished().as_deref(),
                    Some(one_shot.as_slice()),
                    "{target:?}, quality {quality}, ε {epsilon}, {most_slots} slots a step"
                );
            }
        }
    }

    #[test]
    fn a_step_does_no_more_slots_than_it_is_given() {
        let (table, source) = mixed_cut();
        let tf = TransferFunction::new("ramp", &[(0.0, 0.0), (300.0, 1.0)], &[(0.0, [1.0; 3])]);
        let mut build = BlockOracleBuild::new(
            Arc::new(table),
            strata_types::ValueMapping::default(),
            &tf,
            0.001,
            3,
            1.0,
            OracleTarget::Opacity,
        );
        let mut last = 0;
        while !build.step(&source, 2) {
            let (done, total) = build.progress();
            assert_eq!(done, last + 2);
            assert_eq!(total, 18);
            last = done;
        }
        assert!(build.finished().is_some());
        // A finished build stays finished.
        assert!(build.step(&source, 2));
    }

    #[test]
    fn an_empty_cut_is_finished_at_its_first_step() {
        let tf = TransferFunction::new("ramp", &[(0.0, 0.0), (300.0, 1.0)], &[(0.0, [1.0; 3])]);
        let mut build = BlockOracleBuild::new(
            Arc::new(PageTable::new([2, 2, 2])),
            strata_types::ValueMapping::default(),
            &tf,
            0.001,
            3,
            1.0,
            OracleTarget::Opacity,
        );
        assert!(build.step(&Payloads(HashMap::new()), 1));
        assert_eq!(build.finished(), Some(Vec::new()));
    }
}
