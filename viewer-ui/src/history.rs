//! Undo and redo, one history for both viewers (issue 47): the desktop keeps snapshots of its
//! scene (viewer/src/history.rs: transfer function, window, crop, measurements) and label edits
//! in it; the page keeps its link's [`ViewState`] with the navigation cleared
//! ([`edits_of`]).
//!
//! The rules, the desktop's since its first history: a change becomes one step when its
//! gesture ends (no button held), so a drag is undone as a whole, not per frame; a new step
//! clears what could be redone; at most [`MAX_STEPS`] are kept, the oldest dropped first.
//! Besides snapshots a step may be an edit the caller keeps as a difference (`E`: the
//! desktop's brush strokes, whose brick images would be too big to snapshot), reverted and
//! applied again by the caller.

use crate::view_state::ViewState;

/// Steps kept; older ones are dropped.
pub const MAX_STEPS: usize = 200;

/// One undo step: the state before it, or an edit the caller reverts itself.
#[derive(Clone, Debug, PartialEq)]
enum Step<S, E> {
    State(S),
    Edit(E),
}

/// What [`History::undo`] or [`History::redo`] did.
#[derive(Clone, Debug, PartialEq)]
pub enum Stepped<S> {
    /// Nothing was left to undo (or redo).
    Nothing,
    /// The caller puts this state back.
    State(S),
    /// An edit, reverted (or applied again) by the caller's function.
    Edit,
}

/// Undo and redo of snapshots `S` (compared each frame) and edits `E`.
#[derive(Clone, Debug)]
pub struct History<S, E = ()> {
    undo: Vec<Step<S, E>>,
    redo: Vec<Step<S, E>>,
    /// The state the last step ended in.
    committed: S,
    max_steps: usize,
}

impl<S: Clone + PartialEq, E> History<S, E> {
    /// A history whose first state is `state`, keeping [`MAX_STEPS`].
    pub fn new(state: S) -> Self {
        Self::with_depth(state, MAX_STEPS)
    }

    /// A history keeping at most `max_steps` (at least one).
    pub fn with_depth(state: S, max_steps: usize) -> Self {
        History {
            undo: Vec::new(),
            redo: Vec::new(),
            committed: state,
            max_steps: max_steps.max(1),
        }
    }

    /// Called once per frame with the state now: a change with no gesture in progress becomes
    /// an undo step (a drag's frames are one step, its end state against its start).
    pub fn observe(&mut self, now: &S, gesture_in_progress: bool) {
        if gesture_in_progress || *now == self.committed {
            return;
        }
        let before = std::mem::replace(&mut self.committed, now.clone());
        self.push(Step::State(before));
    }

    /// An edit the caller made and keeps (already applied) becomes one undo step.
    pub fn push_edit(&mut self, edit: E) {
        self.push(Step::Edit(edit));
    }

    fn push(&mut self, step: Step<S, E>) {
        self.undo.push(step);
        if self.undo.len() > self.max_steps {
            let excess = self.undo.len() - self.max_steps;
            self.undo.drain(..excess);
        }
        self.redo.clear();
    }

    /// The state the last step ended in.
    pub fn committed(&self) -> &S {
        &self.committed
    }

    /// The state moved without an edit (what a view shows once it opens, not what the user
    /// did): it becomes the current state, no step.
    pub fn rebase(&mut self, state: S) {
        self.committed = state;
    }

    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }

    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }

    /// Undoes the last step, `now` being the state on screen (a change not yet observed is
    /// taken as a step first, so it is what is undone). An edit step is handed to `revert`,
    /// which answers false when it cannot be reverted any more (the desktop's label layer was
    /// closed): that step is dropped and the one before is undone.
    pub fn undo(&mut self, now: &S, mut revert: impl FnMut(&E) -> bool) -> Stepped<S> {
        self.observe(now, false);
        while let Some(step) = self.undo.pop() {
            match step {
                Step::State(previous) => {
                    let current = std::mem::replace(&mut self.committed, previous);
                    self.redo.push(Step::State(current));
                    return Stepped::State(self.committed.clone());
                }
                Step::Edit(edit) => {
                    if revert(&edit) {
                        self.redo.push(Step::Edit(edit));
                        return Stepped::Edit;
                    }
                }
            }
        }
        Stepped::Nothing
    }

    /// Applies the last undone step again; an edit step is handed to `reapply` (false: it is
    /// dropped, as in [`History::undo`]).
    pub fn redo(&mut self, mut reapply: impl FnMut(&E) -> bool) -> Stepped<S> {
        while let Some(step) = self.redo.pop() {
            match step {
                Step::State(next) => {
                    let current = std::mem::replace(&mut self.committed, next);
                    self.undo.push(Step::State(current));
                    return Stepped::State(self.committed.clone());
                }
                Step::Edit(edit) => {
                    if reapply(&edit) {
                        self.undo.push(Step::Edit(edit));
                        return Stepped::Edit;
                    }
                }
            }
        }
        Stepped::Nothing
    }
}

/// `edits` with the navigation of `navigation`: which way the camera looks, the crosshair,
/// a 4-D store's frame, the layout, the mode and the slices' colour map (the desktop's history leaves its camera,
/// crosshair and display choices alone too), and what names the volume and the page's hooks. Everything else in a
/// [`ViewState`] is an edit: the transfer function and preset, the window, the crop box and
/// clip plane, shading and light, the iso value, and any field added later unless it is
/// listed here.
fn with_navigation_of(edits: ViewState, navigation: &ViewState) -> ViewState {
    ViewState {
        mode: navigation.mode,
        azimuth_deg: navigation.azimuth_deg,
        elevation_deg: navigation.elevation_deg,
        zoom: navigation.zoom,
        pan: navigation.pan,
        orthographic: navigation.orthographic,
        layout: navigation.layout,
        cursor: navigation.cursor,
        // The 4-D frame shown is navigation (cine would make a step of every frame).
        frame: navigation.frame,
        colour_map: navigation.colour_map,
        volume_edge: navigation.volume_edge,
        store: navigation.store.clone(),
        image_size: navigation.image_size,
        capture: navigation.capture,
        capture_unconverged: navigation.capture_unconverged,
        bench_frames: navigation.bench_frames,
        ..edits
    }
}

/// The page's undo snapshot of `view`: its edits, the navigation at the defaults (so turning
/// the view or paging a slice is no step).
pub fn edits_of(view: &ViewState) -> ViewState {
    with_navigation_of(view.clone(), &ViewState::default())
}

/// `view` with the edits of `snapshot` put back (an undo or redo), its navigation as it is.
pub fn restore_edits(view: &ViewState, snapshot: &ViewState) -> ViewState {
    with_navigation_of(snapshot.clone(), view)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn undo_state(history: &mut History<i32>, now: i32) -> Stepped<i32> {
        history.undo(&now, |_| false)
    }

    #[test]
    fn a_drag_is_one_step_and_undo_then_redo_walk_it() {
        let mut history = History::<i32>::new(0);
        assert!(!history.can_undo() && !history.can_redo());
        // A drag's frames: 1, 2, 3 with the button held, released at 3.
        for value in [1, 2, 3] {
            history.observe(&value, true);
        }
        assert!(
            !history.can_undo(),
            "nothing is a step while the gesture goes on"
        );
        history.observe(&3, false);
        history.observe(&3, false);
        assert!(history.can_undo());
        assert_eq!(undo_state(&mut history, 3), Stepped::State(0));
        assert!(!history.can_undo() && history.can_redo());
        assert_eq!(history.redo(|_| false), Stepped::State(3));
        assert_eq!(history.redo(|_| false), Stepped::Nothing);
        assert_eq!(undo_state(&mut history, 3), Stepped::State(0));
        assert_eq!(undo_state(&mut history, 0), Stepped::Nothing);
    }

    #[test]
    fn a_new_edit_clears_redo_and_an_unobserved_change_is_undone_first() {
        let mut history = History::<i32>::new(0);
        history.observe(&1, false);
        history.observe(&2, false);
        assert_eq!(undo_state(&mut history, 2), Stepped::State(1));
        history.observe(&5, false);
        assert!(!history.can_redo(), "a new step clears redo");
        // A change made since the last frame (not observed) is the step undone.
        assert_eq!(undo_state(&mut history, 7), Stepped::State(5));
        assert_eq!(undo_state(&mut history, 5), Stepped::State(1));
        assert_eq!(undo_state(&mut history, 1), Stepped::State(0));
    }

    #[test]
    fn the_depth_is_capped_dropping_the_oldest() {
        let mut history = History::<i32>::with_depth(0, 3);
        for value in 1..=10 {
            history.observe(&value, false);
        }
        let mut undone = Vec::new();
        let mut now = 10;
        while let Stepped::State(v) = undo_state(&mut history, now) {
            undone.push(v);
            now = v;
        }
        assert_eq!(undone, [9, 8, 7]);
        assert_eq!(MAX_STEPS, History::<i32>::new(0).max_steps);
    }

    #[test]
    fn edits_are_reverted_by_the_caller_and_stale_ones_are_skipped() {
        let mut history = History::<i32, &str>::new(0);
        history.observe(&1, false);
        history.push_edit("stroke a");
        history.push_edit("stroke b");
        let mut reverted = Vec::new();
        // "stroke b" can no longer be reverted (its layer closed): skipped, "stroke a" undone.
        let stepped = history.undo(&1, |e| {
            reverted.push(*e);
            *e != "stroke b"
        });
        assert_eq!(stepped, Stepped::Edit);
        assert_eq!(reverted, ["stroke b", "stroke a"]);
        assert_eq!(history.undo(&1, |_| true), Stepped::State(0));
        let mut reapplied = Vec::new();
        assert_eq!(history.redo(|_| true), Stepped::State(1));
        assert_eq!(
            history.redo(|e| {
                reapplied.push(*e);
                true
            }),
            Stepped::Edit
        );
        assert_eq!(reapplied, ["stroke a"]);
        assert!(!history.can_redo());
    }

    #[test]
    fn the_pages_snapshot_ignores_navigation_and_keeps_edits() {
        let view = ViewState::default();
        let turned = ViewState {
            azimuth_deg: 80.0,
            elevation_deg: -20.0,
            zoom: 2.0,
            pan: [0.5, 0.25],
            orthographic: true,
            cursor: Some([3.0, 4.0, 5.0]),
            layout: crate::view_state::Layout::Single,
            mode: strata_render::RenderMode::Mip,
            colour_map: strata_slices::ColourMap::Hot,
            ..view.clone()
        };
        assert_eq!(edits_of(&turned), edits_of(&view), "navigation is no edit");
        let windowed = ViewState {
            window: Some([40.0, 400.0]),
            preset: "ct-soft-tissue".into(),
            ..turned.clone()
        };
        assert_ne!(edits_of(&windowed), edits_of(&turned));
        // Undoing puts the edits back and leaves the navigation where it is now.
        let restored = restore_edits(&windowed, &edits_of(&view));
        assert_eq!(restored.window, None);
        assert_eq!(restored.preset, view.preset);
        assert_eq!(restored.azimuth_deg, 80.0);
        assert_eq!(restored.cursor, Some([3.0, 4.0, 5.0]));
        assert_eq!(restored.mode, strata_render::RenderMode::Mip);
        assert_eq!(edits_of(&restored), edits_of(&view));
    }
}
