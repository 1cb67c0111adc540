//! Labels that stick between rounds of interactive refinement.
//!
//! Each round retrains the forest on all strokes so far and predicts again. A forest grown
//! anew gives every voxel a different vote: near a tie between two classes that noise alone
//! flips labels anywhere in the volume, far from where the user drew; one stroke's new rows
//! move the forest's splits everywhere; and the spatial prior then keeps or drops whole
//! components over it. The user sees a correction in one place change the answer elsewhere.
//!
//! The rule ([`hold`]), voxel by voxel, against the labels the previous round showed:
//!
//! - **Near the new strokes, a ramp.** At the stroke the new labels stand; a change needs the
//!   new probabilities to prefer it by a share of `delta` that grows with the distance, in
//!   `ramp` steps, to all of it at the `margin` (the filter bank's halo, the image a scribbled
//!   voxel's features see). A stroke corrects what it touches at once; its surroundings, where
//!   a thin class grows into look-alike tissue, change on evidence.
//! - **Beyond the margin, strong evidence.** A voxel keeps its label unless the new
//!   probabilities prefer the new one by `delta` (0.5 by default: in a choice between two
//!   classes, 3:1 odds). The forest's vote noise (two standard errors at p = 0.5, `1 / sqrt(T)`:
//!   0.1 at 100 trees, 0.18 at 32) lies far below it; on the development volumes the far
//!   changes with a preference under 0.5 broke about as many voxels as they fixed
//!   (BENCHMARKS.md, issue 48).
//! - **The prior's and growth's decisions hold too** (with the rounds' [`Verdicts`]): beyond
//!   the margin a voxel whose forest label did not change keeps the label the previous round
//!   decided for it. A component kept or dropped because a stroke elsewhere changed its
//!   connectivity, or the mass of its class's scribbled component, is not evidence about it.
//!   A label the rule held earlier is not such a decision: it goes when the evidence comes.
//! - **Confirmed by three forests** (`confirm`, `forests`): beyond the margin a change shows
//!   only when the forests of the two rounds before already gave it. On the development
//!   volumes the far drops were a forest over-generalising from one stroke (a thin class
//!   spilling into look-alike tissue, a brain boundary moving everywhere at once, bone marrow
//!   taken for the soft tissue a background stroke covered): the next round's forest shares
//!   that stroke and often still gives the change, so two forests in a row showed it a round
//!   later whatever the next visit drew; a change that survives two further visits' strokes
//!   is one they did not contradict. A visit whose strokes name only the changed-to class
//!   could not contradict it and does not count ([`agree`]): after rounds of vessel strokes
//!   alone, each forest spreads the vessel further into look-alike tissue and all of them
//!   agree. Nor does the forest of such a visit count as the first to give a change: it
//!   proposes its class's spread.
//! - **Growth follows what is shown** ([`follow`]): the boundary band growth fills grows from
//!   the labels the rule shows, not from the round's verdict, so a boundary the rule moved
//!   carries its band with it.
//!
//! The functions are pure and per voxel ([`hold`] takes any span of voxels, a brick row or a
//! whole volume), so the batch robot, the CLI and Python pipeline and the service apply the
//! same rule; its inputs (the previous round's shown labels and verdicts, the new round's
//! strokes, probabilities and verdicts) are what the session's saved history keeps, so undo,
//! load and restart reproduce it.

use serde::{Deserialize, Serialize};

/// Settings of the stability rule.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StableConfig {
    /// Voxels (Chebyshev distance) around the new strokes within which the rule ramps down
    /// (beyond it a change needs the full `delta`).
    pub margin: usize,
    /// How much more probable (0..1) the new label must be than the previous one, beyond the
    /// margin, to replace it.
    pub delta: f32,
    /// Steps of the ramp inside the margin ([`needed`]): the preference a change needs rises
    /// from 0 at the new strokes to `delta` at the margin (0: new labels stand anywhere within
    /// the margin, the rule before issue 48). Absent from older settings: the default.
    #[serde(default = "default_ramp")]
    pub ramp: u8,
    /// Whether beyond the margin the spatial prior's and growth's decisions are held too
    /// ([`hold`]'s verdicts): a voxel whose forest label did not change keeps its label.
    /// Absent from older settings: on.
    #[serde(default = "default_prior")]
    pub prior: bool,
    /// Whether beyond the margin a change must be confirmed by the forests of the rounds
    /// before ([`Self::forests`] in a row; needs the verdicts). Absent from
    /// older settings: the default.
    #[serde(default = "default_confirm")]
    pub confirm: bool,
    /// How many forests in a row must give a far change when [`Self::confirm`] is on (2: the
    /// previous round's forest and this one; at most [`MAX_FORESTS`]; the rounds' [`agree`]
    /// counts the forests before this one only when their rounds' strokes name another class).
    /// Absent from older settings: the default.
    #[serde(default = "default_forests")]
    pub forests: u8,
    /// Whether growth follows the labels shown ([`follow`]): after the rule, a doubtful voxel
    /// the round's growth gave class `c` takes `c` when it touches a shown voxel of `c`, as
    /// many steps as the prior grows. Absent from older settings: the default.
    #[serde(default = "default_follow")]
    pub follow: bool,
}

/// The default of [`StableConfig::follow`].
pub const DEFAULT_FOLLOW: bool = true;

fn default_follow() -> bool {
    DEFAULT_FOLLOW
}

/// The default of [`StableConfig::forests`].
pub const DEFAULT_FORESTS: u8 = 3;

/// The most forests [`StableConfig::forests`] can ask for (and where [`agree`] stops counting).
pub const MAX_FORESTS: u8 = 8;

fn default_forests() -> u8 {
    DEFAULT_FORESTS
}

/// The default of [`StableConfig::confirm`].
pub const DEFAULT_CONFIRM: bool = true;

fn default_confirm() -> bool {
    DEFAULT_CONFIRM
}

fn default_prior() -> bool {
    true
}

/// The default ramp (see the module's notes).
pub const DEFAULT_RAMP: u8 = 4;

fn default_ramp() -> u8 {
    DEFAULT_RAMP
}

impl StableConfig {
    /// Each voxel's [`proximity`] level to the strokes a round added (`new`), as [`Self::hold`]
    /// reads it.
    pub fn levels(&self, new: &crate::Scribbles) -> Vec<u8> {
        proximity_of(new, self.margin, self.ramp)
    }

    /// [`hold`] with these settings over a span of voxels (`level` from [`Self::levels`]);
    /// `forest` is used when [`Self::prior`] is on.
    pub fn hold(
        &self,
        labels: &mut [u16],
        prev: &[u16],
        ev: &Evidence,
        level: &[u8],
        forest: Option<&Verdicts>,
    ) -> u64 {
        hold(
            labels,
            prev,
            ev,
            level,
            self.ramp,
            delta_u8(self.delta),
            forest.filter(|_| self.prior),
            self.confirmations(),
        )
    }

    /// The forests in a row a far change needs ([`hold`]'s `forests`): 0 without confirmation.
    pub fn confirmations(&self) -> u8 {
        if self.confirm {
            self.forests.clamp(2, MAX_FORESTS)
        } else {
            0
        }
    }

    /// [`follow`] over a whole volume of `dims` voxels when [`Self::follow`] is on; `now` is
    /// this round's forest labels and verdict ([`RoundVerdicts`]), `grow` the prior's growth
    /// steps. Returns the voxels it changed.
    pub fn follow(
        &self,
        labels: &mut [u16],
        now: (&[u16], &[u16]),
        dims: [usize; 3],
        grow: u32,
    ) -> u64 {
        if self.follow {
            follow(labels, now.0, now.1, dims, grow)
        } else {
            0
        }
    }
}

/// The default `delta` (see the module's notes).
pub const DEFAULT_DELTA: f32 = 0.5;

impl Default for StableConfig {
    /// The filter bank's halo as the margin (the image a scribbled voxel's features see) and
    /// [`DEFAULT_DELTA`].
    fn default() -> Self {
        StableConfig {
            margin: neuvolex_filters::filter_halo(),
            delta: DEFAULT_DELTA,
            ramp: DEFAULT_RAMP,
            prior: true,
            confirm: DEFAULT_CONFIRM,
            forests: DEFAULT_FORESTS,
            follow: DEFAULT_FOLLOW,
        }
    }
}

/// The voxels within Chebyshev distance `margin` of a marked voxel (a box dilation of
/// `marked` over a `dims` grid, `dims[0]` fastest), one separable pass per axis (x and y plane
/// by plane in parallel, then z).
pub fn near(marked: &[bool], dims: [usize; 3], margin: usize) -> Vec<bool> {
    use rayon::prelude::*;
    let [nx, ny, nz] = dims;
    let mut m = marked.to_vec();
    let plane = nx * ny;
    if m.is_empty() || plane == 0 {
        return m;
    }
    m.par_chunks_mut(plane).for_each(|p| {
        let mut dist = Vec::new();
        for y in 0..ny {
            dilate_line(p, y * nx, 1, nx, margin, &mut dist);
        }
        for x in 0..nx {
            dilate_line(p, x, nx, ny, margin, &mut dist);
        }
    });
    let mut dist = Vec::new();
    for s0 in 0..plane {
        dilate_line(&mut m, s0, plane, nz, margin, &mut dist);
    }
    m
}

/// The voxels within `margin` of a scribbled voxel of `s` ([`near`] over its grid; no passes
/// when nothing is scribbled).
pub fn near_scribbles(s: &crate::Scribbles, margin: usize) -> Vec<bool> {
    let mut marked = vec![false; s.dims.iter().product()];
    s.voxels.iter().for_each(|v| marked[v.0 as usize] = true);
    if s.voxels.is_empty() {
        return marked;
    }
    near(&marked, s.dims, margin)
}

/// Dilates the line `m[s0 + k * stride]`, `k < len`, by `margin` along itself.
fn dilate_line(
    m: &mut [bool],
    s0: usize,
    stride: usize,
    len: usize,
    margin: usize,
    dist: &mut Vec<usize>,
) {
    // Distance to the nearest marked voxel along the line, from both ends.
    dist.clear();
    dist.resize(len, usize::MAX);
    let mut last: Option<usize> = None;
    for (k, d) in dist.iter_mut().enumerate() {
        if m[s0 + k * stride] {
            last = Some(k);
        }
        if let Some(l) = last {
            *d = k - l;
        }
    }
    last = None;
    for k in (0..len).rev() {
        if m[s0 + k * stride] {
            last = Some(k);
        }
        if let Some(l) = last {
            dist[k] = dist[k].min(l - k);
        }
    }
    for (k, &d) in dist.iter().enumerate() {
        m[s0 + k * stride] = d <= margin;
    }
}

/// The probability (u8, 0..=255) that a voxel's class probabilities `px` (one per class index)
/// give output label `l`: its class's (`out_labels[k]` is class `k`'s output label, 0 for the
/// background), for label 0 the background's when it was scribbled, else `255 - max`.
pub fn score(px: &[u8], out_labels: &[u16], bg: Option<usize>, l: u16) -> u8 {
    if l == 0 {
        return match bg {
            Some(k) => px[k],
            None => 255 - px.iter().copied().max().unwrap_or(0),
        };
    }
    out_labels.iter().position(|&o| o == l).map_or(0, |k| px[k])
}

/// Applies the rule to a span of voxels: `labels` (this round's, changed in place), `prev`
/// (the previous round's shown labels), `probs` (this round's u8 probabilities, `out_labels.len()`
/// per voxel), `close` (within the margin of the round's new strokes). `delta` is in u8 steps.
/// Returns the voxels that kept their previous label. The rule of issue 31: [`hold`] with new
/// labels standing anywhere within the margin and no test of the forest's own labels.
pub fn stick(
    labels: &mut [u16],
    prev: &[u16],
    probs: &[u8],
    out_labels: &[u16],
    bg: Option<usize>,
    close: &[bool],
    delta: u8,
) -> u64 {
    let level: Vec<u8> = close.iter().map(|&c| u8::from(!c)).collect();
    hold(
        labels,
        prev,
        &Evidence {
            probs,
            out_labels,
            bg,
        },
        &level,
        0,
        delta,
        None,
        0,
    )
}

/// What the forest and the prior decided, for [`hold`] to hold the prior's and growth's
/// decisions beyond the margin: spans of the same voxels as the labels.
#[derive(Debug, Clone, Copy)]
pub struct Verdicts<'a> {
    /// This round's forest labels (its best class where confident, before the prior).
    pub forest: &'a [u16],
    /// The previous round's forest labels.
    pub forest_before: &'a [u16],
    /// The previous round's labels after the prior and growth, before the rule.
    pub verdict_before: &'a [u16],
    /// How many tested forests in a row gave the previous round's forest label ([`agree`]);
    /// empty where unknown (counted as 1: that forest alone).
    pub agree_before: &'a [u16],
}

/// A round's class probabilities as the rule reads them: u8 per class per voxel
/// (`out_labels.len()` per voxel), the output label of each class index, and the background's
/// class index when it was scribbled.
#[derive(Debug, Clone, Copy)]
pub struct Evidence<'a> {
    /// Probabilities (u8), class-minor.
    pub probs: &'a [u8],
    /// Output label of each class index (0 for the background).
    pub out_labels: &'a [u16],
    /// The background's class index, when scribbled.
    pub bg: Option<usize>,
}

/// How near each voxel lies to the marked voxels (a round's new strokes), in `steps + 1`
/// levels: level `j <= steps` is within `margin * j / steps` voxels (Chebyshev distance; level
/// 0 the marked voxels themselves), level `steps + 1` beyond the margin. With `steps` 0, level 0
/// is anywhere within the margin. One [`near`] pass per level.
pub fn proximity(marked: &[bool], dims: [usize; 3], margin: usize, steps: u8) -> Vec<u8> {
    let s = steps as usize;
    let mut level = vec![steps.saturating_add(1); marked.len()];
    if !marked.iter().any(|&m| m) {
        return level;
    }
    // From the widest radius in, so each voxel ends with its smallest level.
    for j in (0..=s).rev() {
        let r = (margin * j).checked_div(s).unwrap_or(margin);
        let m = if r == 0 {
            marked.to_vec()
        } else {
            near(marked, dims, r)
        };
        level
            .iter_mut()
            .zip(&m)
            .filter(|(_, &m)| m)
            .for_each(|(l, _)| *l = j as u8);
    }
    level
}

/// [`proximity`] of the voxels of scribbles `s`.
pub fn proximity_of(s: &crate::Scribbles, margin: usize, steps: u8) -> Vec<u8> {
    let mut marked = vec![false; s.dims.iter().product()];
    s.voxels.iter().for_each(|v| marked[v.0 as usize] = true);
    proximity(&marked, s.dims, margin, steps)
}

/// The preference (u8 steps) a change needs at proximity `level` ([`proximity`]): `delta`
/// beyond the margin, rising linearly from 0 at the new strokes to `delta` at the margin when
/// `steps > 0`, 0 anywhere within the margin when `steps` is 0.
pub fn needed(level: u8, steps: u8, delta: u8) -> u8 {
    if level > steps {
        delta
    } else if steps == 0 {
        0
    } else {
        (delta as u32 * level as u32 / steps as u32) as u8
    }
}

/// Applies the rule to a span of voxels: `labels` (this round's, changed in place) against
/// `prev` (the labels the previous round showed), with this round's [`Evidence`] and each
/// voxel's [`proximity`] `level` to the round's new strokes. A voxel keeps its previous label
/// unless the new probabilities prefer its new label by [`needed`]`(level, steps, delta)`.
///
/// `forest`, when given ([`Verdicts`]), holds the spatial prior's and growth's decisions too:
/// beyond the margin, a voxel whose forest label did not change, and whose previous label was
/// the previous round's own verdict (not a label the rule held), keeps that label whatever the
/// prior and growth now decide. A component kept or dropped because a stroke elsewhere
/// changed its connectivity or its rivals' mass is not evidence about it.
///
/// With `forests` of 2 or more (and `forest`), beyond the margin a change must also be one the
/// previous `forests - 1` rounds' forests already gave (the previous forest's label there is
/// the new one, and its [`agree`] count at least `forests - 1`): a change shows once
/// `forests - 1` tested forests in a row gave it before this one (a round tests it when its
/// strokes name another class), if this forest still gives it. A forest that over-generalises
/// from one stroke, and is corrected by the next visits, never shows it far away. Below 2, no
/// confirmation.
///
/// Returns the voxels that kept their previous label.
#[allow(clippy::too_many_arguments)]
pub fn hold(
    labels: &mut [u16],
    prev: &[u16],
    ev: &Evidence,
    level: &[u8],
    steps: u8,
    delta: u8,
    forest: Option<&Verdicts>,
    forests: u8,
) -> u64 {
    let nc = ev.out_labels.len().max(1);
    let mut kept = 0;
    for (v, (l, &p)) in labels.iter_mut().zip(prev).enumerate() {
        if *l == p {
            continue;
        }
        let lev = level[v];
        if let Some(f) = forest {
            let same = f.forest[v] == f.forest_before[v] && p == f.verdict_before[v];
            let unconfirmed = forests >= 2
                && (*l != f.forest_before[v]
                    || in_a_row(f.agree_before, v) < u16::from(forests) - 1);
            if lev > steps && (same || unconfirmed) {
                *l = p;
                kept += 1;
                continue;
            }
        }
        let need = needed(lev, steps, delta);
        if need == 0 {
            continue;
        }
        let px = &ev.probs[v * nc..(v + 1) * nc];
        let (new, old) = (
            score(px, ev.out_labels, ev.bg, *l),
            score(px, ev.out_labels, ev.bg, p),
        );
        if (new as i32) < old as i32 + need as i32 {
            *l = p;
            kept += 1;
        }
    }
    kept
}

/// How many forests in a row, ending with this round's, gave each voxel its forest label and
/// were tested on it: a forest counts when its round's new strokes name a class other than that
/// label (`tested`, output labels: [`tested`]). Where the forest label did not change, the
/// previous round's count (`agree_before`, empty where unknown: 1) plus this forest's; where it
/// changed, this forest's alone (1 or 0). At most [`MAX_FORESTS`]. Spans of the same voxels.
///
/// A round whose strokes name only the voxel's class is no test of it: its forest learnt from
/// more of that class alone and grows it wherever it grew before, so its agreement confirms
/// nothing (on the abdomen's aorta alone, three forests after three aorta-only rounds spread
/// the aorta into look-alike tissue far away: a drop of 0.141 in one round; BENCHMARKS.md,
/// issue 48), and a change it is the first to give is that spread, not evidence (on the brain
/// against the rest, a background-only round's forest moved the brain's boundary inward and two
/// tested forests confirmed it: a drop of 0.024). Nor is a round that adds no strokes.
pub fn agree(
    forest: &[u16],
    forest_before: &[u16],
    agree_before: &[u16],
    tested: &[u16],
) -> Vec<u16> {
    forest
        .iter()
        .zip(forest_before)
        .enumerate()
        .map(|(v, (&a, &b))| {
            let step = u16::from(tested.iter().any(|&c| c != a));
            if a == b {
                (in_a_row(agree_before, v) + step).min(u16::from(MAX_FORESTS))
            } else {
                step
            }
        })
        .collect()
}

/// The output labels (0 for the background) the strokes a round added (`new`) name, once
/// each and sorted: [`agree`]'s `tested`.
pub fn tested(new: &crate::Scribbles, background: u32) -> Vec<u16> {
    let mut named: Vec<u32> = new.voxels.iter().map(|&(_, l)| l).collect();
    named.sort_unstable();
    named.dedup();
    let mut t = crate::output_labels(&named, background);
    t.sort_unstable();
    t.dedup();
    t
}

/// Voxel `v`'s count of tested forests in a row in `agree` ([`agree`]; 0 when the forest that
/// first gave its label was not tested): 1 where unknown (a first round, or a round saved
/// before the forests were counted).
fn in_a_row(agree: &[u16], v: usize) -> u16 {
    agree.get(v).map_or(1, |&c| c)
}

/// Growth that follows the labels shown, over a whole volume (`dims`, x fastest): after
/// [`hold`], a doubtful voxel (the round's `forest` label 0) that the round's growth gave
/// class `c` (its `verdict`, so `c` is its most probable class) and that shows another label
/// takes `c` when a 6-neighbour shows `c`, `grow` times. Returns the voxels changed.
///
/// Unlike growth itself, it also replaces a label shown (one the rule held): the rule holds a
/// doubtful voxel's label because growth's decisions are held, not on evidence for it, and
/// growth's verdict names its most probable class. Filling only unlabelled voxels recovered
/// less (7-class brain MRI, round 10: 0.631 against 0.676 mean F1).
///
/// Growth is hysteresis around confident voxels: the boundary band where a voxel's features
/// mix two tissues takes the class of the confident side. [`hold`] holds growth's decisions
/// beyond the margin (a doubtful voxel's forest label, 0, never changes, and it is never a
/// confirmed change), so without this a boundary the rule moved keeps the band of where it
/// was (on the 7-class brain MRI the rule then converged to 0.602 mean F1 at round 10 against
/// 0.671 without it: BENCHMARKS.md, issue 48). Here the band follows what the rule shows; a
/// band around a change the rule held does not move, since the shown neighbour is missing.
pub fn follow(
    labels: &mut [u16],
    forest: &[u16],
    verdict: &[u16],
    dims: [usize; 3],
    grow: u32,
) -> u64 {
    let n = labels.len();
    assert!(forest.len() == n && verdict.len() == n && dims.iter().product::<usize>() == n);
    let todo = follow_todo(0, forest, verdict, labels).collect();
    follow_in(labels, dims, todo, grow)
}

/// The voxels of a span (the first at volume index `start`) that [`follow`] may change: each
/// doubtful voxel that growth gave a class and that shows another label, with that class.
pub fn follow_todo<'a>(
    start: usize,
    forest: &'a [u16],
    verdict: &'a [u16],
    labels: &'a [u16],
) -> impl Iterator<Item = (usize, u16)> + 'a {
    forest
        .iter()
        .zip(verdict)
        .zip(labels)
        .enumerate()
        .filter(|(_, ((&f, &v), &l))| f == 0 && v != 0 && l != v)
        .map(move |(i, ((_, &v), _))| (start + i, v))
}

/// A label volume (x fastest) as [`follow_in`] reads and writes it: one slice, or the bricks
/// of a service that holds them apart.
pub trait LabelGrid {
    /// The label of voxel `i` (0 where nothing is held).
    fn get(&self, i: usize) -> u16;
    /// Sets the label of voxel `i`.
    fn set(&mut self, i: usize, l: u16);
}

impl LabelGrid for [u16] {
    fn get(&self, i: usize) -> u16 {
        self[i]
    }
    fn set(&mut self, i: usize, l: u16) {
        self[i] = l;
    }
}

/// [`follow`] on any [`LabelGrid`] of `dims` voxels, from its candidates `todo` (volume index,
/// the class growth gave it; [`follow_todo`]).
pub fn follow_in<G: LabelGrid + ?Sized>(
    grid: &mut G,
    dims: [usize; 3],
    mut todo: Vec<(usize, u16)>,
    grow: u32,
) -> u64 {
    let (sx, sy) = (dims[0], dims[0] * dims[1]);
    let mut changed = 0;
    let mut add = Vec::new();
    for _ in 0..grow {
        add.clear();
        todo.retain(|&(i, c)| {
            let (x, y, z) = (i % sx, (i / sx) % dims[1], i / sy);
            let touches = (x > 0 && grid.get(i - 1) == c)
                || (x + 1 < dims[0] && grid.get(i + 1) == c)
                || (y > 0 && grid.get(i - sx) == c)
                || (y + 1 < dims[1] && grid.get(i + sx) == c)
                || (z > 0 && grid.get(i - sy) == c)
                || (z + 1 < dims[2] && grid.get(i + sy) == c);
            if touches {
                add.push((i, c));
            }
            !touches
        });
        if add.is_empty() {
            break;
        }
        for &(i, c) in &add {
            grid.set(i, c);
        }
        changed += add.len() as u64;
    }
    changed
}

/// The strokes added since `before`: the voxels of `now` that `before` did not scribble, when
/// `now` keeps every voxel of `before` with its label (a later round of the same user), else
/// `None` (strokes were erased or relabelled: no round to hold to).
pub fn added(before: &crate::Scribbles, now: &crate::Scribbles) -> Option<crate::Scribbles> {
    if before.dims != now.dims {
        return None;
    }
    // Both are sorted by voxel, one entry each: one merge.
    let mut old = before.voxels.iter().peekable();
    let mut new = Vec::new();
    for &(v, l) in &now.voxels {
        match old.peek() {
            Some(&&(ov, ol)) if ov == v => {
                if ol != l {
                    return None;
                }
                old.next();
            }
            Some(&&(ov, _)) if ov < v => return None,
            _ => new.push((v, l)),
        }
    }
    old.next().is_none().then_some(crate::Scribbles {
        dims: now.dims,
        voxels: new,
    })
}

/// A previous result that a new classification holds to with the rule: what it showed and the
/// scribbles it came from (same settings and features; the caller checks).
#[derive(Clone)]
pub struct Hold {
    /// The scribbles of the previous result.
    pub scribbles: crate::Scribbles,
    /// Its output labels per voxel (x fastest), as shown.
    pub labels: Vec<u16>,
    /// The rule's margin and `delta`.
    pub config: StableConfig,
    /// The previous result's own decisions (`None`: unknown, the prior's and growth's
    /// decisions are then held only by the probabilities).
    pub verdicts: Option<RoundVerdicts>,
}

/// A round's own decisions per voxel (x fastest), kept so that the next round holds them
/// ([`Verdicts`]).
#[derive(Clone, Default, PartialEq)]
pub struct RoundVerdicts {
    /// The forest's labels (its best class where confident, before the prior).
    pub forest: Vec<u16>,
    /// The labels after the prior and growth, before the rule.
    pub verdict: Vec<u16>,
    /// How many tested forests in a row gave each voxel its forest label ([`agree`]); empty
    /// where unknown (a first round, or one saved before they were counted).
    pub agree: Vec<u16>,
}

impl RoundVerdicts {
    /// This round's verdicts, with [`agree`] counted from the previous round's and the output
    /// labels the round's new strokes name (`before`, as [`Hold::verdicts_before`] gives them;
    /// `None` or another grid: every count 1).
    pub fn after(
        forest: Vec<u16>,
        verdict: Vec<u16>,
        before: Option<(&RoundVerdicts, Vec<u16>)>,
    ) -> Self {
        let agree = match before.filter(|(b, _)| b.forest.len() == forest.len()) {
            Some((b, tested)) => agree(&forest, &b.forest, &b.agree, &tested),
            None => Vec::new(),
        };
        RoundVerdicts {
            forest,
            verdict,
            agree,
        }
    }

    /// [`Verdicts`] of a span `r` of voxels, this round's forest labels `forest` against these
    /// (the previous round's).
    pub fn span<'a>(&'a self, forest: &'a [u16], r: std::ops::Range<usize>) -> Verdicts<'a> {
        Verdicts {
            forest,
            forest_before: &self.forest[r.clone()],
            verdict_before: &self.verdict[r.clone()],
            agree_before: self.agree.get(r).unwrap_or(&[]),
        }
    }
}

impl std::fmt::Debug for RoundVerdicts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RoundVerdicts")
            .field("voxels", &self.forest.len())
            .finish()
    }
}

impl Hold {
    /// The held round's verdicts when scribbles `scr` extend its own (the new round continues
    /// it, so its forests in a row count on from the held round's), with the output labels the
    /// strokes added since name ([`tested`]; `background` is the background's scribble label).
    pub fn verdicts_before(
        &self,
        scr: &crate::Scribbles,
        background: u32,
    ) -> Option<(&RoundVerdicts, Vec<u16>)> {
        let v = self.verdicts.as_ref()?;
        added(&self.scribbles, scr).map(|new| (v, tested(&new, background)))
    }
}

impl std::fmt::Debug for Hold {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Hold")
            .field("scribbled", &self.scribbles.voxels.len())
            .field("voxels", &self.labels.len())
            .field("config", &self.config)
            .finish()
    }
}

/// A probability (clamped to 0..1) in the u8 steps the service keeps and [`stick`] compares,
/// rounded to the nearest step: the one quantisation of the service, the robot and the pipeline.
pub fn to_u8(p: f32) -> u8 {
    (p.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// `delta` (a probability) in the u8 steps [`stick`] compares.
pub fn delta_u8(delta: f32) -> u8 {
    to_u8(delta)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn added_strokes_are_the_new_voxels_of_a_superset() {
        let s = |v: &[(u64, u32)]| crate::Scribbles {
            dims: [4, 4, 4],
            voxels: v.to_vec(),
        };
        let before = s(&[(3, 1), (9, 2)]);
        assert_eq!(
            added(&before, &s(&[(1, 2), (3, 1), (5, 1), (9, 2), (20, 1)])),
            Some(s(&[(1, 2), (5, 1), (20, 1)]))
        );
        assert_eq!(added(&before, &before), Some(s(&[])));
        assert_eq!(added(&s(&[]), &before), Some(before.clone()));
        assert_eq!(added(&before, &s(&[(3, 1), (9, 1)])), None, "relabelled");
        assert_eq!(added(&before, &s(&[(3, 1)])), None, "erased last");
        assert_eq!(added(&before, &s(&[(4, 1), (9, 2)])), None, "erased first");
        let mut other = before.clone();
        other.dims = [4, 4, 5];
        assert_eq!(added(&before, &other), None, "another grid");
    }

    #[test]
    fn near_is_a_box_dilation() {
        let d = [9, 7, 6];
        let n: usize = d.iter().product();
        let at = |x: usize, y: usize, z: usize| (z * d[1] + y) * d[0] + x;
        let mut marked = vec![false; n];
        marked[at(2, 3, 4)] = true;
        let m = near(&marked, d, 1);
        for z in 0..d[2] {
            for y in 0..d[1] {
                for x in 0..d[0] {
                    let inside = x.abs_diff(2) <= 1 && y.abs_diff(3) <= 1 && z.abs_diff(4) <= 1;
                    assert_eq!(m[at(x, y, z)], inside, "{x} {y} {z}");
                }
            }
        }
        assert!(near(&marked, d, 0) == marked);
        assert!(near(&marked, d, 9).iter().all(|&v| v));
        assert!(!near(&vec![false; n], d, 3).iter().any(|&v| v));
        let scr = crate::Scribbles {
            dims: d,
            voxels: vec![(at(2, 3, 4) as u64, 1)],
        };
        assert_eq!(near_scribbles(&scr, 1), m);
        let none = crate::Scribbles {
            dims: d,
            voxels: Vec::new(),
        };
        assert!(!near_scribbles(&none, 3).iter().any(|&v| v));
        // Random marks against the distance itself.
        let mut rng = neuvolex_bricks::rng::Rng::new(5);
        let marked: Vec<bool> = (0..n).map(|_| rng.f32() < 0.02).collect();
        let pts: Vec<[usize; 3]> = (0..n)
            .filter(|&i| marked[i])
            .map(|i| [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])])
            .collect();
        for margin in [0, 1, 2] {
            let m = near(&marked, d, margin);
            for (i, &got) in m.iter().enumerate() {
                let q = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
                let want = pts
                    .iter()
                    .any(|p| (0..3).all(|a| p[a].abs_diff(q[a]) <= margin));
                assert_eq!(got, want, "voxel {q:?}, margin {margin}");
            }
        }
    }

    #[test]
    fn a_wobble_sticks_and_clear_evidence_or_a_near_stroke_changes() {
        // Classes: index 0 = label 1, index 1 = label 2, index 2 = background.
        let out = [1u16, 2, 0];
        let bg = Some(2);
        let probs: Vec<u8> = vec![
            120, 130, 5, // 0: 2 beats 1 by 10 steps: a wobble, 1 sticks
            40, 200, 15, // 1: 2 beats 1 by 160: it changes
            120, 130, 5, // 2: a wobble, but near the new stroke: it changes
            100, 20,
            135, // 3: previous 1, new 0 (background 135 beats 100 by 35 < 40): sticks
            10, 20, 225, // 4: previous 1, new 0 with clear evidence: changes
            128, 127, 0, // 5: unchanged
        ];
        let prev = vec![1u16, 1, 1, 1, 1, 1];
        let mut labels = vec![2u16, 2, 2, 0, 0, 1];
        let close = [false, false, true, false, false, false];
        let kept = stick(&mut labels, &prev, &probs, &out, bg, &close, 40);
        assert_eq!(labels, vec![1, 2, 2, 1, 0, 1]);
        assert_eq!(kept, 2);
        // delta 0: the new labels whenever they are at least as probable.
        let mut labels = vec![2u16, 2, 2, 0, 0, 1];
        assert_eq!(stick(&mut labels, &prev, &probs, &out, bg, &close, 0), 0);
        // Without a scribbled background, label 0 scores 255 - max.
        assert_eq!(score(&[100, 20], &[1, 2], None, 0), 155);
        // A class the new forest does not know scores 0, so it never holds a voxel.
        assert_eq!(score(&[100, 20], &[1, 2], None, 7), 0);
    }

    #[test]
    fn proximity_levels_are_distance_bands() {
        let d = [13, 11, 9];
        let n: usize = d.iter().product();
        let mut rng = neuvolex_bricks::rng::Rng::new(11);
        let marked: Vec<bool> = (0..n).map(|_| rng.f32() < 0.004).collect();
        let pts: Vec<[usize; 3]> = (0..n)
            .filter(|&i| marked[i])
            .map(|i| [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])])
            .collect();
        assert!(!pts.is_empty());
        for (margin, steps) in [(8, 4), (6, 3), (5, 0), (8, 1)] {
            let level = proximity(&marked, d, margin, steps);
            for (i, &got) in level.iter().enumerate() {
                let q = [i % d[0], (i / d[0]) % d[1], i / (d[0] * d[1])];
                // The Chebyshev distance to the nearest marked voxel, by brute force.
                let dist = pts
                    .iter()
                    .map(|p| (0..3).map(|a| p[a].abs_diff(q[a])).max().unwrap())
                    .min()
                    .unwrap();
                let want = if steps == 0 {
                    u8::from(dist > margin)
                } else {
                    (0..=steps)
                        .find(|&j| dist <= margin * j as usize / steps as usize)
                        .unwrap_or(steps + 1)
                };
                assert_eq!(got, want, "voxel {q:?} at {dist}, margin {margin}/{steps}");
            }
        }
        // Nothing marked: every voxel beyond.
        assert!(proximity(&vec![false; n], d, 8, 4).iter().all(|&l| l == 5));
    }

    #[test]
    fn the_preference_needed_ramps_up_to_delta_at_the_margin() {
        assert_eq!(
            (0..=5).map(|l| needed(l, 4, 64)).collect::<Vec<_>>(),
            vec![0, 16, 32, 48, 64, 64]
        );
        // Without a ramp: nothing inside the margin, delta beyond.
        assert_eq!((needed(0, 0, 64), needed(1, 0, 64)), (0, 64));
        // The extremes: no delta holds nothing, a full one everything beyond.
        assert_eq!((needed(5, 4, 0), needed(5, 4, 255)), (0, 255));
    }

    #[test]
    fn hold_ramps_inside_the_margin_and_can_hold_the_forest_s_own_labels() {
        // Class index 0 = label 1, index 1 = background; previous label 1 everywhere, the new
        // round says background with a preference of 40 u8 steps (140 against 100).
        let out = [1u16, 0];
        let probs: Vec<u8> = [100u8, 140].repeat(6);
        let ev = Evidence {
            probs: &probs,
            out_labels: &out,
            bg: Some(1),
        };
        let prev = vec![1u16; 6];
        // Levels 0..=5 with a ramp of 4 and delta 64: needs 0, 16, 32, 48, 64, 64.
        let level = [0u8, 1, 2, 3, 4, 5];
        let mut l = vec![0u16; 6];
        assert_eq!(hold(&mut l, &prev, &ev, &level, 4, 64, None, 0), 3);
        assert_eq!(l, vec![0, 0, 0, 1, 1, 1]);
        // stick is the rule without a ramp: new labels stand anywhere within the margin.
        let mut l = vec![0u16; 6];
        let close = [true, true, true, true, true, false];
        assert_eq!(stick(&mut l, &prev, &probs, &out, Some(1), &close, 64), 1);
        assert_eq!(l, vec![0, 0, 0, 0, 0, 1]);
        // With the verdicts: beyond the margin a voxel whose forest label did not change keeps
        // its label even on clear evidence (the prior or growth changed it), unless that label
        // was one the rule held; one whose forest label changed follows the evidence.
        let v = Verdicts {
            forest: &[1, 1, 1, 1, 1, 0, 1],
            forest_before: &[1, 1, 1, 1, 1, 1, 1],
            verdict_before: &[1, 1, 1, 1, 1, 1, 0],
            agree_before: &[],
        };
        let prev = vec![1u16; 7];
        let strong: Vec<u8> = [10u8, 240].repeat(7);
        let ev = Evidence {
            probs: &strong,
            out_labels: &out,
            bg: Some(1),
        };
        // The rule beyond and inside the margin (levels 5 and 0, 2, 4) with `forests`.
        let run = |v: &Verdicts, forests: u8| {
            let mut l = vec![0u16; 7];
            let kept = hold(
                &mut l,
                &prev,
                &ev,
                &[5, 5, 0, 2, 4, 5, 5],
                4,
                64,
                Some(v),
                forests,
            );
            (kept, l)
        };
        assert_eq!(run(&v, 0), (2, vec![1, 1, 0, 0, 0, 0, 0]));
        // Confirmed by two forests: beyond the margin only a change the previous forest
        // already gave shows. Voxel 5's forest gives 0 for the first time: held. Voxel 6's
        // gave 0 before too, and the rule held its label then (its verdict was 0): released.
        let v = Verdicts {
            forest: &[1, 1, 1, 1, 1, 0, 0],
            forest_before: &[1, 1, 1, 1, 1, 1, 0],
            verdict_before: &[1, 1, 1, 1, 1, 1, 0],
            agree_before: &[],
        };
        assert_eq!(run(&v, 2), (3, vec![1, 1, 0, 0, 0, 1, 0]));
        // Confirmed by three forests: voxel 6's change shows only where the forest before the
        // previous one gave it too (the previous round's count 2), not on two forests alone.
        for (agree_before, want) in [
            (&[] as &[u16], 1u16),
            (&[0u16; 7][..], 1),
            (&[1u16; 7][..], 1),
            (&[2u16; 7][..], 0),
        ] {
            let (_, l) = run(&Verdicts { agree_before, ..v }, 3);
            assert_eq!(l, vec![1, 1, 0, 0, 0, 1, want], "{agree_before:?}");
        }
    }

    #[test]
    fn tested_names_the_classes_of_new_strokes() {
        let new = crate::Scribbles {
            dims: [4, 2, 1],
            voxels: vec![(0, 255), (3, 4), (5, 255), (7, 1)],
        };
        assert_eq!(tested(&new, 255), vec![0, 1, 4]);
        let none = crate::Scribbles {
            dims: [4, 2, 1],
            voxels: vec![],
        };
        assert!(tested(&none, 255).is_empty());
        // A held round's verdicts come with the classes its continuation added.
        let h = Hold {
            scribbles: crate::Scribbles {
                dims: [4, 2, 1],
                voxels: vec![(0, 255)],
            },
            labels: vec![0; 8],
            config: StableConfig::default(),
            verdicts: Some(RoundVerdicts::after(vec![0; 8], vec![0; 8], None)),
        };
        let (_, t) = h.verdicts_before(&new, 255).expect("extends");
        assert_eq!(t, vec![0, 1, 4]);
        let relabelled = crate::Scribbles {
            dims: [4, 2, 1],
            voxels: vec![(0, 1)],
        };
        assert!(h.verdicts_before(&relabelled, 255).is_none());
    }

    #[test]
    fn agree_counts_forests_in_a_row() {
        // Strokes of the background (0) and class 1 test every voxel: counts go on where the
        // forest label stayed, back to 1 where it changed.
        let both = [0, 1];
        assert_eq!(
            agree(&[1, 2, 0, 3], &[1, 1, 0, 3], &[], &both),
            vec![2, 1, 2, 2]
        );
        // A stored 0 (the forest that first gave the label was not tested) counts from 0.
        assert_eq!(
            agree(&[1, 2, 0, 3], &[1, 1, 0, 3], &[2, 5, 0, 8], &both),
            vec![3, 1, 1, 8]
        );
        // Strokes of class 1 alone test no voxel whose forest gives 1: its count stays (voxel
        // 0), while the others' go on; a round without strokes tests nothing, and a change it
        // gives starts at 0.
        assert_eq!(
            agree(&[1, 2, 0, 3], &[1, 1, 0, 3], &[2, 5, 0, 8], &[1]),
            vec![2, 1, 1, 8]
        );
        assert_eq!(
            agree(&[1, 2, 0, 3], &[1, 1, 0, 3], &[2, 5, 3, 4], &[]),
            vec![2, 0, 3, 4]
        );
        // A change to the only class the strokes name is that class's spread: it starts at 0,
        // and the next tested forest that still gives it is the first to count.
        let spread = agree(&[1, 2], &[1, 1], &[2, 2], &[2]);
        assert_eq!(spread, vec![3, 0]);
        assert_eq!(agree(&[1, 2], &[1, 2], &spread, &[0, 2]), vec![4, 1]);
        let first = RoundVerdicts::after(vec![1, 0], vec![1, 0], None);
        assert!(first.agree.is_empty(), "a first round counts nothing");
        let second = RoundVerdicts::after(vec![1, 2], vec![1, 2], Some((&first, both.to_vec())));
        assert_eq!(second.agree, vec![2, 1]);
        let third = RoundVerdicts::after(vec![1, 2], vec![1, 2], Some((&second, both.to_vec())));
        assert_eq!(third.agree, vec![3, 2]);
        // Three rounds of class 2 strokes alone: the change to 2 is still one forest's.
        let mut only = second.clone();
        for _ in 0..3 {
            only = RoundVerdicts::after(vec![1, 2], vec![1, 2], Some((&only, vec![2])));
        }
        assert_eq!(only.agree, vec![5, 1]);
        let other =
            RoundVerdicts::after(vec![1, 2, 3], vec![1, 2, 3], Some((&third, both.to_vec())));
        assert!(other.agree.is_empty(), "another grid counts nothing");
        let c = StableConfig::default();
        assert_eq!(c.confirmations(), DEFAULT_FORESTS);
        assert_eq!(
            StableConfig {
                confirm: false,
                ..c
            }
            .confirmations(),
            0
        );
        assert_eq!(StableConfig { forests: 0, ..c }.confirmations(), 2);
        assert_eq!(
            StableConfig { forests: 99, ..c }.confirmations(),
            MAX_FORESTS
        );
    }

    #[test]
    fn the_default_holds_a_half() {
        assert_eq!(delta_u8(0.25), 64);
        assert_eq!(delta_u8(DEFAULT_DELTA), 128);
        assert_eq!(delta_u8(2.0), 255);
        let c = StableConfig::default();
        assert_eq!(
            (c.margin, c.delta, c.ramp, c.prior, c.confirm),
            (
                neuvolex_filters::filter_halo(),
                DEFAULT_DELTA,
                DEFAULT_RAMP,
                true,
                DEFAULT_CONFIRM
            )
        );
        // Settings saved before the ramp existed read back with today's ramp and prior hold.
        let old: StableConfig = serde_json::from_str(r#"{"margin": 24, "delta": 0.25}"#).unwrap();
        assert_eq!((old.ramp, old.prior), (DEFAULT_RAMP, true));
        assert_eq!((old.confirm, old.follow), (DEFAULT_CONFIRM, DEFAULT_FOLLOW));
        assert_eq!(old.forests, DEFAULT_FORESTS);
    }

    #[test]
    fn growth_follows_the_shown_labels_for_its_steps_only() {
        // One row of 10 voxels: the rule shows class 1 on 0..3, nothing on 3..8, and held
        // label 2 on 8..10 (label 3 in the second case). The forest is confident on 0..3 (1)
        // and on 9 (2), doubtful on 3..9; growth gave 3..6 class 1 and 6..9 class 2 (its
        // verdict, from before the rule).
        let dims = [10, 1, 1];
        let forest = [1, 1, 1, 0, 0, 0, 0, 0, 0, 2];
        let verdict = [1, 1, 1, 1, 1, 1, 2, 2, 2, 2];
        let shown = [1, 1, 1, 0, 0, 0, 0, 0, 2, 2];
        let mut l = shown.to_vec();
        assert_eq!(follow(&mut l, &forest, &verdict, dims, 2), 4);
        assert_eq!(l, [1, 1, 1, 1, 1, 0, 2, 2, 2, 2], "two steps, not three");
        // A label shown (held) is replaced too, and growth goes on from there.
        let mut l = [1, 1, 1, 3, 0, 0, 0, 0, 2, 2];
        assert_eq!(follow(&mut l, &forest, &verdict, dims, 2), 4);
        assert_eq!(l, [1, 1, 1, 1, 1, 0, 2, 2, 2, 2]);
        let mut l = shown.to_vec();
        assert_eq!(follow(&mut l, &forest, &verdict, dims, 0), 0);
        assert_eq!(l, shown);
        // A confident voxel is never followed, and nothing grows without a shown neighbour.
        let mut l = [2, 2, 2, 2, 2, 2, 2, 2, 2, 2];
        assert_eq!(follow(&mut l, &forest, &verdict, dims, 4), 0);
        // The setting turns it off.
        let off = StableConfig {
            follow: false,
            ..StableConfig::default()
        };
        let mut l = shown.to_vec();
        assert_eq!(off.follow(&mut l, (&forest, &verdict), dims, 2), 0);
        assert_eq!(l, shown);
        // In 3-D, along every axis, the same as growing from the shown labels alone.
        let dims = [5, 4, 3];
        let n = 60;
        let mut rng = neuvolex_bricks::rng::Rng::new(3);
        for _ in 0..20 {
            let forest: Vec<u16> = (0..n).map(|_| (rng.f32() < 0.3) as u16).collect();
            let verdict: Vec<u16> = forest
                .iter()
                .map(|&f| {
                    if f == 0 {
                        1 + (rng.f32() < 0.5) as u16
                    } else {
                        f
                    }
                })
                .collect();
            let shown: Vec<u16> = (0..n).map(|_| (rng.f32() * 3.0) as u16).collect();
            let mut l = shown.clone();
            follow(&mut l, &forest, &verdict, dims, 2);
            // The reference: each step, from the labels after the step before.
            let mut r = shown.clone();
            for _ in 0..2 {
                let before = r.clone();
                for i in 0..n {
                    let (x, y, z) = (i % 5, (i / 5) % 4, i / 20);
                    let c = verdict[i];
                    let nb = [
                        (x > 0).then(|| i - 1),
                        (x < 4).then(|| i + 1),
                        (y > 0).then(|| i - 5),
                        (y < 3).then(|| i + 5),
                        (z > 0).then(|| i - 20),
                        (z < 2).then(|| i + 20),
                    ];
                    if forest[i] == 0
                        && before[i] != c
                        && nb.iter().flatten().any(|&j| before[j] == c)
                    {
                        r[i] = c;
                    }
                }
            }
            assert_eq!(l, r);
        }
    }
}
