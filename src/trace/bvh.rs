//! BVH over the surfels' disks: bounds, binned-SAH build, refit, quality, traversal.
//!
//! Bounds: a surfel contributes α = o·G ≥ 1/255 only where u² + v² ≤ r² with
//! r² = 2·ln(o·255), an ellipse of semi-axes r·s_u along t_u and r·s_v along t_v. Its exact AABB
//! has half-extent sqrt((r s_u t_u[a])² + (r s_v t_v[a])²) along world axis a. Surfels with
//! o < 1/255 get an empty box (never hit, ignored by unions); a refit gives them a box again.
//!
//! Layout: a flat BVH2 in depth-first order (left child = node + 1, right child stored), leaves
//! hold ≤ 8 primitives, each leaf's hit data packed as one structure-of-arrays block
//! (`PrimBlock`) tested in one f32x8 pass; the SAH charges a leaf about one node visit
//! whatever its count (`leaf_cost`), so leaves come out fuller. Build: binned SAH (16 bins per
//! axis), subtrees above 8k primitives built in parallel (rayon::join) and concatenated.
//! Refit: blocks and leaf boxes in parallel, then one reverse pass over the interior nodes
//! (children always follow their parent).
//!
//! The BVH2 is then collapsed into an 8-wide BVH (SoA child boxes, one f32x8 slab test per
//! node) which the rays traverse; a refit refits the BVH2 and copies its boxes into the slots.
//! Each child slot also holds the normal cone of its subtree (`NormalCone`): a one-sided ray
//! skips a child all of whose surfels face away from it — per-node back-face culling, which
//! lets rays leaving a surface skip the patch they start from.
//!
//! Traversal (`gather`): a closest-hit-style traversal that keeps the k nearest valid hits
//! beyond a (t, index) key in a sorted array and culls nodes beyond the current k-th distance
//! (or before the key's depth). Children visited near to far.

use crate::surfels::{Surfels, rotation_from_quat, sigmoid};
use crate::trace::{ALPHA_MAX, ALPHA_MIN, MAX_CHUNK, TraceSettings};
use rayon::prelude::*;
use std::mem::MaybeUninit;
use wide::f32x8;

/// One BVH node: 32 bytes, aligned so a node never straddles a cache line.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
pub(crate) struct Node {
    pub min: [f32; 3],
    /// Interior: index of the right child (the left is the next node). Leaf: first primitive.
    pub right_or_first: u32,
    pub max: [f32; 3],
    /// 0 for interior nodes, else the primitive count.
    pub count: u32,
}

/// What a hit test needs, per primitive (scattered into the leaves' [`PrimBlock`]s).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Prim {
    pub mean: [f32; 3],
    /// t_u / s_u and t_v / s_v: u = tu_s·p, v = tv_s·p.
    pub tu_s: [f32; 3],
    pub tv_s: [f32; 3],
    pub normal: [f32; 3],
    pub opacity: f32,
    /// 2·ln(255·o): u² + v² beyond this gives α < 1/255 (negative when o < 1/255).
    pub rho_max: f32,
    /// The surfel's index in `Surfels`.
    pub index: u32,
    /// Also hit from behind (a dark occluder, `TraceSettings::back_occluders`).
    pub back_occluder: bool,
}

/// Width of the traversed BVH, and the lanes of a leaf block.
pub(crate) const W: usize = 8;

/// One leaf's ≤ 8 primitives as structure of arrays, so the leaf is tested in one f32x8 pass
/// (no per-primitive branches). Unused lanes have a zero normal (never facing the ray) and
/// rho_max −1 (never inside).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub(crate) struct PrimBlock {
    pub normal: [[f32; W]; 3],
    pub mean: [[f32; W]; 3],
    pub tu_s: [[f32; W]; 3],
    pub tv_s: [[f32; W]; 3],
    pub opacity: [f32; W],
    pub rho_max: [f32; W],
    /// Surfel index per lane (u32::MAX in unused lanes).
    pub index: [u32; W],
    /// Bit l set when lane l is a back occluder (hit from behind too, when tracing one-sided).
    pub back_lanes: u32,
}

impl PrimBlock {
    const EMPTY: PrimBlock = PrimBlock {
        normal: [[0.0; W]; 3],
        mean: [[0.0; W]; 3],
        tu_s: [[0.0; W]; 3],
        tv_s: [[0.0; W]; 3],
        opacity: [0.0; W],
        rho_max: [-1.0; W],
        index: [u32::MAX; W],
        back_lanes: 0,
    };

    fn set(&mut self, lane: usize, p: &Prim) {
        for a in 0..3 {
            self.normal[a][lane] = p.normal[a];
            self.mean[a][lane] = p.mean[a];
            self.tu_s[a][lane] = p.tu_s[a];
            self.tv_s[a][lane] = p.tv_s[a];
        }
        self.opacity[lane] = p.opacity;
        self.rho_max[lane] = p.rho_max;
        self.index[lane] = p.index;
        self.back_lanes = (self.back_lanes & !(1 << lane)) | ((p.back_occluder as u32) << lane);
    }

    fn lanes(&self) -> impl Iterator<Item = usize> + '_ {
        (0..W).filter(|&l| self.index[l] != u32::MAX)
    }
}
/// Child reference flag: a leaf, encoded LEAF_BIT | its block's index.
const LEAF_BIT: u32 = 1 << 31;
/// Child reference of an unused slot.
const EMPTY_CHILD: u32 = u32::MAX;
/// Traversal stack of the wide BVH: ≤ 7 entries per level (depth ≤ 64 SAH + 32 count splits),
/// plus room for `push_children`'s 8-entry store.
const WIDE_STACK: usize = 7 * 96 + 16;

/// An 8-wide node: child boxes as structure of arrays (one f32x8 per bound and axis) and the
/// child references. Unused slots have the box [+∞, +∞], which no ray enters.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub(crate) struct WideNode {
    pub bmin: [[f32; W]; 3],
    pub bmax: [[f32; W]; 3],
    /// Each child's normal cone as (axis xyz, threshold): a one-sided ray with unit direction
    /// d̂ cannot hit a front face below the child when axis·d̂ > threshold (see [`NormalCone`]).
    pub cone: [[f32; W]; 4],
    pub child: [u32; W],
    /// Bit j set when slot j holds a child (fills what would be padding).
    pub used: u32,
}

impl WideNode {
    fn empty() -> Self {
        WideNode {
            bmin: [[f32::INFINITY; W]; 3],
            bmax: [[f32::INFINITY; W]; 3],
            cone: [[0.0; W], [0.0; W], [0.0; W], [f32::INFINITY; W]],
            child: [EMPTY_CHILD; W],
            used: 0,
        }
    }
    fn set_box(&mut self, j: usize, nd: &Node, cone: &NormalCone) {
        for a in 0..3 {
            self.bmin[a][j] = nd.min[a];
            self.bmax[a][j] = nd.max[a];
            self.cone[a][j] = cone.axis[a];
        }
        self.cone[3][j] = cone.cull_threshold();
    }
}

/// The normals of a subtree's hittable primitives (opacity ≥ 1/255) all lie within `angle` of
/// `axis`. A one-sided ray only hits faces with n·d < 0; if every n is within θ of the axis and
/// d̂ is within 90° − θ of it (axis·d̂ > sin θ), every n·d > 0 and the subtree can be skipped —
/// back-face culling per node: rays leaving a surface skip the patch they start on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct NormalCone {
    pub axis: [f32; 3],
    /// Half-angle in radians; negative for a subtree with no hittable primitive.
    pub angle: f32,
}

/// Slack added to every cone's half-angle, so a culled subtree's n·d̂ ≥ sin(1e-3) stays far
/// above the f32 rounding of the leaf's own facing test.
const CONE_MARGIN: f32 = 1e-3;

impl NormalCone {
    const EMPTY: NormalCone = NormalCone { axis: [0.0; 3], angle: -1.0 };

    /// Threshold on axis·d̂ above which the subtree is culled: −∞ when it holds nothing
    /// hittable, +∞ (never) when the cone is too wide to cull anything.
    fn cull_threshold(&self) -> f32 {
        if self.angle < 0.0 {
            return f32::NEG_INFINITY;
        }
        let a = self.angle + CONE_MARGIN;
        if a >= std::f32::consts::FRAC_PI_2 { f32::INFINITY } else { a.sin() }
    }

    fn of_block(b: &PrimBlock) -> NormalCone {
        let normal = |l: usize| [b.normal[0][l], b.normal[1][l], b.normal[2][l]];
        let hittable = || b.lanes().filter(|&l| b.rho_max[l] >= 0.0);
        let mut sum = [0.0f32; 3];
        let mut any = false;
        for l in hittable() {
            any = true;
            for a in 0..3 {
                sum[a] += normal(l)[a];
            }
        }
        if !any {
            return NormalCone::EMPTY;
        }
        // A back occluder is hit from either side: no direction can skip it.
        if hittable().any(|l| b.back_lanes & (1 << l) != 0) {
            return NormalCone { axis: [0.0; 3], angle: std::f32::consts::PI };
        }
        let Some(axis) = normalised(sum) else { return NormalCone { axis: [0.0; 3], angle: std::f32::consts::PI } };
        let min_dot = hittable().map(|l| dot(axis, normal(l))).fold(1.0f32, f32::min);
        NormalCone { axis, angle: angle_of(min_dot) }
    }

    fn merge(l: &NormalCone, r: &NormalCone) -> NormalCone {
        if l.angle < 0.0 {
            return *r;
        }
        if r.angle < 0.0 {
            return *l;
        }
        let wide = NormalCone { axis: [0.0; 3], angle: std::f32::consts::PI };
        let Some(axis) = normalised(std::array::from_fn(|a| l.axis[a] + r.axis[a])) else { return wide };
        let angle = (angle_of(dot(axis, l.axis)) + l.angle).max(angle_of(dot(axis, r.axis)) + r.angle);
        NormalCone { axis, angle: angle.min(std::f32::consts::PI) }
    }
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn normalised(v: [f32; 3]) -> Option<[f32; 3]> {
    let l = dot(v, v).sqrt();
    (l > 1e-6).then(|| v.map(|x| x / l))
}

/// An upper bound of acos(cos) (in radians) that is cheap: Abramowitz & Stegun 4.4.45,
/// |error| ≤ 6.8e-5, plus 1e-4 for that error and for unit vectors that are not exactly unit.
fn angle_of(cos: f32) -> f32 {
    let x = cos.clamp(-1.0, 1.0);
    let a = x.abs();
    let r = (1.0 - a).sqrt() * (1.5707288 + a * (-0.2121144 + a * (0.0742610 - 0.0187293 * a)));
    (if x >= 0.0 { r } else { std::f32::consts::PI - r }) + 1e-4
}

#[cfg(test)]
pub(crate) fn normal_cones_for_test(t: &Tracer) -> Vec<NormalCone> {
    normal_cones(&t.nodes, &t.blocks)
}

/// Normal cone of every BVH2 node: leaves in parallel, then one reverse pass over the interior
/// nodes (children always follow their parent).
fn normal_cones(nodes: &[Node], blocks: &[PrimBlock]) -> Vec<NormalCone> {
    let mut cones: Vec<NormalCone> = nodes
        .par_iter()
        .with_min_len(1024)
        .map(|nd| {
            if nd.count == 0 {
                return NormalCone::EMPTY;
            }
            NormalCone::of_block(&blocks[nd.right_or_first as usize])
        })
        .collect();
    for k in (0..nodes.len()).rev() {
        let nd = &nodes[k];
        if nd.count == 0 {
            cones[k] = NormalCone::merge(&cones[k + 1], &cones[nd.right_or_first as usize]);
        }
    }
    cones
}

fn node_area(nd: &Node) -> f32 {
    area(&[nd.min[0], nd.min[1], nd.min[2], nd.max[0], nd.max[1], nd.max[2]])
}

fn leaf_ref(nd: &Node) -> u32 {
    LEAF_BIT | nd.right_or_first
}

/// The cones widened by the grazing tolerance γ = asin(`grazing_sin`): a ray then skips a
/// subtree only when every face in it is more than γ past edge-on, as the leaves test.
fn widened(mut cones: Vec<NormalCone>, grazing_sin: f32) -> Vec<NormalCone> {
    if grazing_sin > 0.0 {
        let angle = grazing_sin.min(1.0).asin();
        for c in cones.iter_mut().filter(|c| c.angle >= 0.0) {
            c.angle += angle;
        }
    }
    cones
}

/// Collapse the BVH2 into an 8-wide BVH: each wide node takes up to 8 BVH2 descendants,
/// opening the interior descendant of largest area first (the standard greedy collapse).
fn collapse(nodes: &[Node], cones: &[NormalCone]) -> (Vec<WideNode>, Vec<[u32; W]>) {
    let mut wide = Vec::new();
    let mut src = Vec::new();
    if nodes.is_empty() {
        return (wide, src);
    }
    fn rec(nodes: &[Node], cones: &[NormalCone], b: usize, wide: &mut Vec<WideNode>, src: &mut Vec<[u32; W]>) -> u32 {
        let id = wide.len();
        wide.push(WideNode::empty());
        src.push([u32::MAX; W]);
        let mut kids: Vec<usize> =
            if nodes[b].count > 0 { vec![b] } else { vec![b + 1, nodes[b].right_or_first as usize] };
        while kids.len() < W {
            let open = (0..kids.len())
                .filter(|&j| nodes[kids[j]].count == 0)
                .max_by(|&x, &y| node_area(&nodes[kids[x]]).total_cmp(&node_area(&nodes[kids[y]])));
            let Some(j) = open else { break };
            let c = kids[j];
            kids[j] = c + 1;
            kids.push(nodes[c].right_or_first as usize);
        }
        for (j, &c) in kids.iter().enumerate() {
            let r = if nodes[c].count > 0 { leaf_ref(&nodes[c]) } else { rec(nodes, cones, c, wide, src) };
            wide[id].child[j] = r;
            wide[id].used |= 1 << j;
            wide[id].set_box(j, &nodes[c], &cones[c]);
            src[id][j] = c as u32;
        }
        id as u32
    }
    rec(nodes, cones, 0, &mut wide, &mut src);
    (wide, src)
}

/// The acceleration structure plus the settings rays are traced with.
#[derive(Clone, Debug)]
pub struct Tracer {
    pub settings: TraceSettings,
    pub(crate) nodes: Vec<Node>,
    /// The BVH2 collapsed to an 8-wide BVH (what rays traverse); `wide_src` names the BVH2 node
    /// behind each child slot (u32::MAX for an empty slot) so a refit can copy the boxes.
    pub(crate) wide: Vec<WideNode>,
    pub(crate) wide_src: Vec<[u32; W]>,
    /// One block per leaf, in leaf order (a leaf node's `right_or_first` is its block); a lane's
    /// `index` names its surfel (u32::MAX for an unused lane), which a refit reloads.
    pub(crate) blocks: Vec<PrimBlock>,
    /// Surfel count at the build.
    pub(crate) count: usize,
    /// SAH cost (normalised by the root area) right after the build, and now.
    pub(crate) built_cost: f32,
    pub(crate) cost: f32,
}

type Aabb = [f32; 6]; // min xyz, max xyz

const EMPTY: Aabb =
    [f32::INFINITY, f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];

fn union(a: &Aabb, b: &Aabb) -> Aabb {
    [a[0].min(b[0]), a[1].min(b[1]), a[2].min(b[2]), a[3].max(b[3]), a[4].max(b[4]), a[5].max(b[5])]
}

fn area(b: &Aabb) -> f32 {
    let (x, y, z) = (b[3] - b[0], b[4] - b[1], b[5] - b[2]);
    if x < 0.0 || y < 0.0 || z < 0.0 { 0.0 } else { 2.0 * (x * y + y * z + z * x) }
}

/// Bounds of surfel `i`'s α ≥ 1/255 ellipse, and its packed hit data.
fn surfel_bounds(s: &Surfels, i: usize, back_occluders: Option<&[bool]>) -> (Aabb, Prim) {
    let r = rotation_from_quat(s.quats[i]);
    let sc = s.scale(i);
    let o = sigmoid(s.opacity_logits[i]);
    let (su, sv) = (sc[0].max(1e-20), sc[1].max(1e-20));
    let m = s.means[i];
    // ρ² at which α falls to ALPHA_MIN (one log for the hit data and the bounds).
    let rho_sq = 2.0 * (o / ALPHA_MIN).ln();
    let prim = Prim {
        mean: m,
        tu_s: r[0].map(|x| x / su),
        tv_s: r[1].map(|x| x / sv),
        normal: r[2],
        opacity: o,
        rho_max: if o >= ALPHA_MIN { rho_sq } else { -1.0 },
        index: i as u32,
        back_occluder: back_occluders.is_some_and(|b| b[i]),
    };
    if !(o >= ALPHA_MIN) {
        return (EMPTY, prim);
    }
    let rr = rho_sq.max(0.0).sqrt();
    let (ru, rv) = (rr * su, rr * sv);
    let mut b = EMPTY;
    for a in 0..3 {
        let h = ((ru * r[0][a]).powi(2) + (rv * r[1][a]).powi(2)).sqrt();
        // A little slack so f32 rounding in the hit test never leaves a valid hit outside.
        let h = h * (1.0 + 1e-5) + 1e-7 * m[a].abs();
        b[a] = m[a] - h;
        b[a + 3] = m[a] + h;
    }
    (b, prim)
}

/// SAH cost of a leaf of n primitives, relative to one BVH2 node visit: the block test costs
/// about one visit whatever n ≤ 8 (one f32x8 pass), plus the per-lane follow-up of its hits.
/// (Measured on the trained spheres scene and the `surface` bench scene: a cost of n, the plain
/// SAH, gave leaves of ~2.7 primitives and 1.2–1.4× slower rays.)
fn leaf_cost(n: usize) -> f32 {
    1.0 + 0.5 * n as f32
}

const BINS: usize = 16;
const MAX_LEAF: usize = 8;
const PAR_THRESHOLD: usize = 8192;
/// Cost of a node visit relative to one primitive test (SAH).
const C_TRAV: f32 = 1.0;
const MAX_SAH_DEPTH: u32 = 64;

/// Build the subtree over `idx` (surfel indices); node indices and leaf `first` are relative to
/// this subtree (`prim_base` is the offset of `idx` in the full order).
fn build_subtree(idx: &mut [u32], boxes: &[Aabb], cents: &[[f32; 3]], prim_base: u32, depth: u32) -> Vec<Node> {
    let n = idx.len();
    let mut bounds = EMPTY;
    let mut cb = EMPTY;
    for &i in idx.iter() {
        bounds = union(&bounds, &boxes[i as usize]);
        let c = cents[i as usize];
        cb = union(&cb, &[c[0], c[1], c[2], c[0], c[1], c[2]]);
    }
    let leaf = |bounds: Aabb| {
        vec![Node {
            min: [bounds[0], bounds[1], bounds[2]],
            right_or_first: prim_base,
            max: [bounds[3], bounds[4], bounds[5]],
            count: n as u32,
        }]
    };
    if n <= 2 {
        return leaf(bounds);
    }
    // Binned SAH over the centroid bounds.
    let mut best = (f32::INFINITY, 0usize, 0usize); // cost, axis, split bin (left = bins < split)
    for axis in 0..3 {
        let (lo, hi) = (cb[axis], cb[axis + 3]);
        if !(hi > lo) {
            continue;
        }
        let scale = BINS as f32 / (hi - lo);
        let mut bb = [EMPTY; BINS];
        let mut bc = [0usize; BINS];
        for &i in idx.iter() {
            let b = (((cents[i as usize][axis] - lo) * scale) as usize).min(BINS - 1);
            bb[b] = union(&bb[b], &boxes[i as usize]);
            bc[b] += 1;
        }
        let mut right_area = [0.0f32; BINS];
        let mut right_count = [0usize; BINS];
        let (mut acc, mut cnt) = (EMPTY, 0);
        for b in (1..BINS).rev() {
            acc = union(&acc, &bb[b]);
            cnt += bc[b];
            right_area[b] = area(&acc);
            right_count[b] = cnt;
        }
        let (mut acc, mut cnt) = (EMPTY, 0);
        for split in 1..BINS {
            acc = union(&acc, &bb[split - 1]);
            cnt += bc[split - 1];
            if cnt == 0 || right_count[split] == 0 {
                continue;
            }
            let cost = area(&acc) * cnt as f32 + right_area[split] * right_count[split] as f32;
            if cost < best.0 {
                best = (cost, axis, split);
            }
        }
    }
    let parent_area = area(&bounds);
    let split_cost = if parent_area > 0.0 { C_TRAV + best.0 / parent_area } else { f32::INFINITY };
    let mid;
    // Beyond MAX_SAH_DEPTH split by count, so the depth (and the traversal stack) stays bounded.
    if best.0.is_finite() && depth < MAX_SAH_DEPTH {
        if n <= MAX_LEAF && split_cost >= leaf_cost(n) {
            return leaf(bounds);
        }
        let (axis, split) = (best.1, best.2);
        let (lo, hi) = (cb[axis], cb[axis + 3]);
        let scale = BINS as f32 / (hi - lo);
        let mut l = 0;
        for k in 0..n {
            let b = (((cents[idx[k] as usize][axis] - lo) * scale) as usize).min(BINS - 1);
            if b < split {
                idx.swap(k, l);
                l += 1;
            }
        }
        mid = l;
    } else {
        // All centroids coincide (or the tree is deep): split by count.
        if n <= MAX_LEAF {
            return leaf(bounds);
        }
        mid = n / 2;
    }
    let (left_idx, right_idx) = idx.split_at_mut(mid);
    let (left, right) = if n > PAR_THRESHOLD {
        rayon::join(
            || build_subtree(left_idx, boxes, cents, prim_base, depth + 1),
            || build_subtree(right_idx, boxes, cents, prim_base + mid as u32, depth + 1),
        )
    } else {
        (
            build_subtree(left_idx, boxes, cents, prim_base, depth + 1),
            build_subtree(right_idx, boxes, cents, prim_base + mid as u32, depth + 1),
        )
    };
    let mut nodes = Vec::with_capacity(1 + left.len() + right.len());
    let right_start = 1 + left.len() as u32;
    nodes.push(Node {
        min: [bounds[0], bounds[1], bounds[2]],
        right_or_first: right_start,
        max: [bounds[3], bounds[4], bounds[5]],
        count: 0,
    });
    nodes.extend(left.into_iter().map(|mut nd| {
        if nd.count == 0 {
            nd.right_or_first += 1;
        }
        nd
    }));
    nodes.extend(right.into_iter().map(|mut nd| {
        if nd.count == 0 {
            nd.right_or_first += right_start;
        }
        nd
    }));
    nodes
}

/// The settings' back-occluder flags, which must be one per surfel.
fn back_occluders<'a>(surfels: &Surfels, settings: &'a TraceSettings) -> Option<&'a [bool]> {
    let flags = settings.back_occluders.as_deref()?;
    assert_eq!(flags.len(), surfels.len(), "trace: back_occluders must hold one flag per surfel");
    Some(flags)
}

impl Tracer {
    /// Build the BVH over all surfels (binned SAH).
    pub fn build(surfels: &Surfels, settings: &TraceSettings) -> Tracer {
        let n = surfels.len();
        let occluders = back_occluders(surfels, settings);
        let (boxes, prims): (Vec<Aabb>, Vec<Prim>) =
            (0..n).into_par_iter().map(|i| surfel_bounds(surfels, i, occluders)).unzip();
        let mut idx: Vec<u32> = (0..n as u32).collect();
        let mut nodes = if n == 0 { Vec::new() } else { build_subtree(&mut idx, &boxes, &surfels.means, 0, 0) };
        assert!(n < (1 << 28), "trace: {n} surfels exceed the BVH's 2^28 primitive limit");
        // Each leaf's primitives go into one block; the leaf then names its block.
        let mut blocks = Vec::new();
        for nd in nodes.iter_mut().filter(|nd| nd.count > 0) {
            let first = nd.right_or_first as usize;
            let mut block = PrimBlock::EMPTY;
            for (lane, &i) in idx[first..first + nd.count as usize].iter().enumerate() {
                block.set(lane, &prims[i as usize]);
            }
            nd.right_or_first = blocks.len() as u32;
            blocks.push(block);
        }
        let (wide, wide_src) = collapse(&nodes, &widened(normal_cones(&nodes, &blocks), settings.grazing_sin));
        let mut t =
            Tracer { settings: settings.clone(), nodes, wide, wide_src, blocks, count: n, built_cost: 0.0, cost: 0.0 };
        t.cost = t.sah_cost();
        t.built_cost = t.cost;
        t
    }

    /// Recompute every box from the surfels' current parameters, keeping the tree. When the
    /// surfel count changed this rebuilds instead.
    pub fn refit(&mut self, surfels: &Surfels) {
        if surfels.len() != self.count {
            *self = Tracer::build(surfels, &self.settings);
            return;
        }
        // Blocks and their boxes in parallel, then the leaves, then the interior nodes
        // bottom-up (children follow their parent).
        let mut block_boxes = vec![EMPTY; self.blocks.len()];
        let occluders = back_occluders(surfels, &self.settings);
        self.blocks.par_iter_mut().zip(block_boxes.par_iter_mut()).for_each(|(block, bb)| {
            for lane in 0..W {
                let i = block.index[lane];
                if i != u32::MAX {
                    let (b, p) = surfel_bounds(surfels, i as usize, occluders);
                    block.set(lane, &p);
                    *bb = union(bb, &b);
                }
            }
        });
        self.nodes.par_iter_mut().with_min_len(1024).filter(|nd| nd.count > 0).for_each(|nd| {
            let b = block_boxes[nd.right_or_first as usize];
            nd.min = [b[0], b[1], b[2]];
            nd.max = [b[3], b[4], b[5]];
        });
        for k in (0..self.nodes.len()).rev() {
            let nd = self.nodes[k];
            if nd.count > 0 {
                continue;
            }
            let (l, r) = (&self.nodes[k + 1], &self.nodes[nd.right_or_first as usize]);
            let b = union(
                &[l.min[0], l.min[1], l.min[2], l.max[0], l.max[1], l.max[2]],
                &[r.min[0], r.min[1], r.min[2], r.max[0], r.max[1], r.max[2]],
            );
            self.nodes[k].min = [b[0], b[1], b[2]];
            self.nodes[k].max = [b[3], b[4], b[5]];
        }
        let nodes = &self.nodes;
        let cones = widened(normal_cones(nodes, &self.blocks), self.settings.grazing_sin);
        self.wide.par_iter_mut().zip(self.wide_src.par_iter()).for_each(|(w, src)| {
            for (j, &b) in src.iter().enumerate() {
                if b != u32::MAX {
                    w.set_box(j, &nodes[b as usize], &cones[b as usize]);
                }
            }
        });
        self.cost = self.sah_cost();
    }

    /// True when the surfel count differs from the build's, or refits have degraded the tree's
    /// SAH cost beyond `settings.rebuild_ratio` × its cost after the build.
    pub fn needs_rebuild(&self) -> bool {
        self.cost > self.settings.rebuild_ratio * self.built_cost
    }

    /// True when the tree was built for a different surfel count (rebuild before tracing).
    pub fn count_mismatch(&self, surfels: &Surfels) -> bool {
        surfels.len() != self.count
    }

    /// SAH cost now divided by its cost after the build (the refit quality measure).
    pub fn quality_ratio(&self) -> f32 {
        if self.built_cost > 0.0 { self.cost / self.built_cost } else { 1.0 }
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Σ over nodes of area/root-area × (C_trav for interior, count for leaves).
    fn sah_cost(&self) -> f32 {
        let Some(root) = self.nodes.first() else { return 0.0 };
        let ra = area(&[root.min[0], root.min[1], root.min[2], root.max[0], root.max[1], root.max[2]]);
        if ra <= 0.0 {
            return 0.0;
        }
        let mut c = 0.0f64;
        for nd in &self.nodes {
            let a = area(&[nd.min[0], nd.min[1], nd.min[2], nd.max[0], nd.max[1], nd.max[2]]) as f64;
            c += a * if nd.count == 0 { C_TRAV as f64 } else { nd.count as f64 };
        }
        (c / ra as f64) as f32
    }
}

/// A ray prepared for traversal.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PreparedRay {
    pub o: [f32; 3],
    pub d: [f32; 3],
    pub inv_d: [f32; 3],
    /// d / |d| (zero for a zero direction), for the normal-cone test, and |d|.
    pub d_unit: [f32; 3],
    pub len: f32,
    /// The ray's [`Ray::skip_below`](crate::trace::Ray::skip_below) plane, and whether it is set.
    pub skip: [f32; 4],
    pub skips: bool,
}

impl PreparedRay {
    pub fn new(o: [f32; 3], d: [f32; 3]) -> Self {
        let len = dot(d, d).sqrt();
        let d_unit = if len > 0.0 { d.map(|x| x / len) } else { [0.0; 3] };
        PreparedRay { o, d, inv_d: d.map(|x| 1.0 / x), d_unit, len, skip: [0.0; 4], skips: false }
    }

    pub fn from_ray(ray: &crate::trace::Ray) -> Self {
        let mut r = Self::new(ray.origin, ray.dir);
        let p = ray.skip_below;
        r.skips = p[0] != 0.0 || p[1] != 0.0 || p[2] != 0.0;
        if r.skips {
            r.skip = p;
        }
        r
    }
}

/// One gathered hit: depth, surfel index, leaf slot, α.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Hit {
    pub t: f32,
    pub index: u32,
    pub slot: u32,
    pub alpha: f32,
}

/// The bits of an f32 as a u32 of the same order (−0 just below +0; NaN does not occur).
#[inline(always)]
fn ord_bits(t: f32) -> u32 {
    let b = t.to_bits();
    if b >> 31 != 0 { !b } else { b | 0x8000_0000 }
}

/// A traversal stack entry: the entry distance's ordered bits above the child reference, so
/// entries compare as (distance, child). Never 0: its distance bits are nonzero for every
/// non-NaN distance (ord_bits is 0 only for the NaN 0xFFFFFFFF, which slab tests built from
/// fast_min/fast_max never produce).
#[inline(always)]
fn stack_entry(child: u32, t: f32) -> u64 {
    ((ord_bits(t) as u64) << 32) | child as u64
}

/// A traversal stack: entries below the stack size were written; the rest is scratch.
type WideStack = [MaybeUninit<u64>; WIDE_STACK];

/// Take the hit children `mask` of a wide node (slot j: reference `child[j]`, entry distance
/// `t_near[j]`): the nearest becomes the next entry to visit (returned, 0 when `mask` is
/// empty) and the others are pushed farthest first, so they pop near to far. Returns the new
/// stack size and the next entry. Needs `sp + 8 ≤ WIDE_STACK` (the sorted path stores 8).
///
/// With AVX-512 two or more children are ordered by a branch-free bitonic network: on trained
/// scenes, where nodes have several hit children, the insertion loop's branches mispredicted
/// (forward 7–13 % faster on the bench and trained scenes; BENCHMARKS.md, session 22).
#[inline(always)]
fn push_children(stack: &mut WideStack, sp: usize, t_near: f32x8, child: &[u32; W], mask: u32) -> (usize, u64) {
    if mask & mask.wrapping_sub(1) == 0 {
        // No child or one (the common case in sparse regions): nothing pushed.
        if mask == 0 {
            return (sp, 0);
        }
        let j = mask.trailing_zeros() as usize;
        let tn: [f32; W] = t_near.into();
        return (sp, stack_entry(child[j], tn[j]));
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    {
        use std::arch::x86_64::*;
        assert!(sp + W <= WIDE_STACK);
        let cnt = mask.count_ones() as i64;
        // SAFETY: AVX-512F is enabled at compile time (the cfg above); the unaligned store
        // writes stack[sp..sp + 8], in bounds by the assert.
        unsafe {
            let bits: __m256i = std::mem::transmute(t_near);
            // ord_bits lane-wise: negative → !b, else b | sign.
            let ord = _mm256_xor_si256(bits, _mm256_or_si256(_mm256_srai_epi32(bits, 31), _mm256_set1_epi32(i32::MIN)));
            let keys = _mm512_or_si512(
                _mm512_slli_epi64(_mm512_cvtepu32_epi64(ord), 32),
                _mm512_cvtepu32_epi64(_mm256_loadu_si256(child.as_ptr() as *const __m256i)),
            );
            // Slots not in `mask` become u64::MAX and sort last.
            let mut v = _mm512_mask_mov_epi64(_mm512_set1_epi64(-1), mask as u8, keys);
            let nearest = _mm512_reduce_min_epu64(v);
            // Bitonic sorting network, ascending: 6 layers of compare-exchange with the lane
            // partner given by the permutation; `max` marks the lanes that keep the larger.
            macro_rules! layer {
                ($a:expr, $b:expr, $c:expr, $d:expr, $e:expr, $f:expr, $g:expr, $h:expr, $max:expr) => {{
                    let p = _mm512_permutexvar_epi64(_mm512_set_epi64($h, $g, $f, $e, $d, $c, $b, $a), v);
                    v = _mm512_mask_blend_epi64($max, _mm512_min_epu64(v, p), _mm512_max_epu64(v, p));
                }};
            }
            layer!(1, 0, 3, 2, 5, 4, 7, 6, 0b0110_0110);
            layer!(2, 3, 0, 1, 6, 7, 4, 5, 0b0011_1100);
            layer!(1, 0, 3, 2, 5, 4, 7, 6, 0b0101_1010);
            layer!(4, 5, 6, 7, 0, 1, 2, 3, 0b1111_0000);
            layer!(2, 3, 0, 1, 6, 7, 4, 5, 0b1100_1100);
            layer!(1, 0, 3, 2, 5, 4, 7, 6, 0b1010_1010);
            // Stack slot sp + i takes the (cnt − 1 − i)-th nearest: the farthest deepest, the
            // nearest (returned) left out.
            let idx = _mm512_and_si512(
                _mm512_sub_epi64(_mm512_set1_epi64(cnt - 1), _mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0)),
                _mm512_set1_epi64(7),
            );
            _mm512_storeu_si512(stack.as_mut_ptr().add(sp) as *mut __m512i, _mm512_permutexvar_epi64(idx, v));
            (sp + cnt as usize - 1, nearest)
        }
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx512f")))]
    {
        // Insertion into the pushed run [base, sp), kept in descending order.
        let tn: [f32; W] = t_near.into();
        let (base, mut sp, mut mask) = (sp, sp, mask);
        while mask != 0 {
            let j = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            let e = stack_entry(child[j], tn[j]);
            let mut q = sp;
            // SAFETY: q − 1 ≥ base was written by this loop.
            while q > base && unsafe { stack[q - 1].assume_init() } < e {
                stack[q] = stack[q - 1];
                q -= 1;
            }
            stack[q] = MaybeUninit::new(e);
            sp += 1;
        }
        // SAFETY: two or more entries were written above `base`.
        (sp - 1, unsafe { stack[sp - 1].assume_init() })
    }
}

#[inline(always)]
fn key_less(t: f32, i: u32, t2: f32, i2: u32) -> bool {
    t < t2 || (t == t2 && i < i2)
}

impl Tracer {
    /// Gather the `k` nearest valid hits with key (t, index) > `after`, within (t_min, t_max],
    /// sorted by key into `out`; returns how many.
    ///
    /// `trans0` is the ray's transmittance before these hits and `stop_below` the
    /// compositing cut-off: once the gathered prefix brings trans0 · Π(1 − α) below it (the
    /// product in the caller's order, so the same hit is found), nothing beyond that hit can
    /// be composited and the cull distance drops to it. Pass `stop_below` 0 to gather all k.
    ///
    /// Traverses the 8-wide BVH: one f32x8 slab test per node gives the entry distance of all
    /// children; the nearest hit child is visited next and the others pushed far to near with
    /// their entry distance (`push_children`), so a pop is culled by a compare when the k-th
    /// distance has since dropped below it (the same test as re-running the slab, as the
    /// box's exit is ≥ its entry).
    ///
    /// `hint` sees the surfel index of every hit as it enters the set, so the caller can
    /// prefetch its payload while the traversal goes on (a hit may still be displaced).
    pub(crate) fn gather(
        &self,
        r: &PreparedRay,
        after: (f32, u32),
        k: usize,
        (trans0, stop_below): (f32, f32),
        out: &mut [Hit; MAX_CHUNK],
        hint: &impl Fn(u32),
    ) -> usize {
        if self.wide.is_empty() {
            return 0;
        }
        let k = k.clamp(1, MAX_CHUNK);
        let lo = after.0.max(self.settings.t_min);
        let mut n = 0usize;
        let mut cull = self.settings.t_max;
        // Π (1 − α) over the gathered hits, kept up to date so the exact early-termination scan
        // runs only once the set can reach the cut-off.
        let mut kept = 1.0f32;
        let o = [f32x8::splat(r.o[0]), f32x8::splat(r.o[1]), f32x8::splat(r.o[2])];
        let inv = [f32x8::splat(r.inv_d[0]), f32x8::splat(r.inv_d[1]), f32x8::splat(r.inv_d[2])];
        let lo_v = f32x8::splat(lo);
        let du = r.d_unit.map(f32x8::splat);
        let two_sided = self.settings.two_sided;
        let mut stack: WideStack = [MaybeUninit::uninit(); WIDE_STACK];
        let mut sp = 0usize;
        // The next entry to visit is kept out of the stack (the nearest child of the last
        // node tested); `next` is 0 when the stack supplies it.
        let mut next = stack_entry(0, lo);
        loop {
            let entry = if next != 0 {
                std::mem::replace(&mut next, 0)
            } else if sp > 0 {
                sp -= 1;
                // SAFETY: entries below `sp` were written (push_children writes, then bumps).
                unsafe { stack[sp].assume_init() }
            } else {
                break;
            };
            let node = entry as u32;
            // `+ 0.0` turns a −0 cull into +0, so an entry at +0 is kept as `tn > cull` would.
            if ((entry >> 32) as u32) > ord_bits(cull + 0.0) {
                continue;
            }
            if node & LEAF_BIT != 0 {
                let block = (node & !LEAF_BIT) as usize;
                self.leaf_hits(block, r, after, k, (trans0, stop_below), out, (&mut n, &mut kept), &mut cull, hint);
                continue;
            }
            let nd = &self.wide[node as usize];
            let mut t_near = lo_v;
            let mut t_far = f32x8::splat(cull);
            for a in 0..3 {
                let t0 = (f32x8::from(nd.bmin[a]) - o[a]) * inv[a];
                let t1 = (f32x8::from(nd.bmax[a]) - o[a]) * inv[a];
                // fast_min/max return the second operand on NaN: a NaN axis (0 · ∞) is ignored.
                t_near = t0.fast_min(t1).fast_max(t_near);
                t_far = t0.fast_max(t1).fast_min(t_far);
            }
            let mut hit = t_near.simd_le(t_far);
            if r.skips {
                // Every centre in a child lies in its box: cull the box when its highest point
                // along the plane normal is below the skip plane.
                let mut top = f32x8::ZERO;
                for a in 0..3 {
                    let n = f32x8::splat(r.skip[a]);
                    top += (f32x8::from(nd.bmin[a]) * n).fast_max(f32x8::from(nd.bmax[a]) * n);
                }
                hit &= !top.simd_lt(f32x8::splat(r.skip[3]));
            }
            if !two_sided {
                let facing_away =
                    f32x8::from(nd.cone[0]) * du[0] + f32x8::from(nd.cone[1]) * du[1] + f32x8::from(nd.cone[2]) * du[2];
                hit &= !facing_away.simd_gt(f32x8::from(nd.cone[3]));
            }
            let mask = hit.to_bitmask();
            (sp, next) = push_children(&mut stack, sp, t_near, &nd.child, mask & nd.used);
        }
        n
    }

    /// Test the ≤ 8 primitives of one leaf block at once, then insert the lanes that hit into
    /// the sorted k-array (few do: the exact key order, α and the insertion are scalar).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn leaf_hits(
        &self,
        block: usize,
        r: &PreparedRay,
        after: (f32, u32),
        k: usize,
        (trans0, stop_below): (f32, f32),
        out: &mut [Hit; MAX_CHUNK],
        (n, kept): (&mut usize, &mut f32),
        cull: &mut f32,
        hint: &impl Fn(u32),
    ) {
        let (t_min, t_max) = (self.settings.t_min, self.settings.t_max);
        let p = &self.blocks[block];
        let v = |a: &[f32; W]| f32x8::from(*a);
        let d = r.d.map(f32x8::splat);
        let zero = f32x8::ZERO;
        // Facing: one-sided rays only hit faces with n·d < |d| sin γ (front faces and back
        // faces within the grazing tolerance) and back occluders with n·d > 0; two-sided any
        // with n·d ≠ 0 (unused lanes have a zero normal, so n·d = 0).
        let b = v(&p.normal[0]) * d[0] + v(&p.normal[1]) * d[1] + v(&p.normal[2]) * d[2];
        let facing = if self.settings.two_sided {
            b.simd_ne(zero).to_bitmask()
        } else {
            let graze = f32x8::splat(self.settings.grazing_sin * r.len);
            (b.simd_lt(graze) & b.simd_ne(zero)).to_bitmask() | (b.simd_gt(zero).to_bitmask() & p.back_lanes)
        };
        if facing == 0 {
            return;
        }
        let w: [f32x8; 3] = std::array::from_fn(|a| v(&p.mean[a]) - f32x8::splat(r.o[a]));
        let t = (v(&p.normal[0]) * w[0] + v(&p.normal[1]) * w[1] + v(&p.normal[2]) * w[2]) / b;
        // The key test (t, index) > after is finished per lane below; here only t ≥ after.t.
        let in_range = t.simd_gt(f32x8::splat(t_min))
            & t.simd_le(f32x8::splat(t_max.min(*cull)))
            & t.simd_ge(f32x8::splat(after.0));
        let q: [f32x8; 3] = std::array::from_fn(|a| t * d[a] - w[a]);
        let u = v(&p.tu_s[0]) * q[0] + v(&p.tu_s[1]) * q[1] + v(&p.tu_s[2]) * q[2];
        let vv = v(&p.tv_s[0]) * q[0] + v(&p.tv_s[1]) * q[1] + v(&p.tv_s[2]) * q[2];
        let rho = u * u + vv * vv;
        let inside = rho.simd_le(v(&p.rho_max) * f32x8::splat(1.0 + 1e-5));
        let mut mask = facing & (in_range & inside).to_bitmask();
        if r.skips {
            let height = v(&p.mean[0]) * f32x8::splat(r.skip[0])
                + v(&p.mean[1]) * f32x8::splat(r.skip[1])
                + v(&p.mean[2]) * f32x8::splat(r.skip[2]);
            mask &= !height.simd_lt(f32x8::splat(r.skip[3])).to_bitmask();
        }
        if mask == 0 {
            return;
        }
        let (t_arr, rho_arr): ([f32; W], [f32; W]) = (t.into(), rho.into());
        while mask != 0 {
            let lane = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            let (t, index) = (t_arr[lane], p.index[lane]);
            if t > *cull || !key_less(after.0, after.1, t, index) {
                continue;
            }
            if *n == k && !key_less(t, index, out[k - 1].t, out[k - 1].index) {
                continue;
            }
            let alpha = (p.opacity[lane] * (-0.5 * rho_arr[lane]).exp()).min(ALPHA_MAX);
            if !(alpha >= ALPHA_MIN) {
                continue;
            }
            // Insertion into the sorted array (drops the k-th when full).
            if *n == k {
                *kept /= 1.0 - out[k - 1].alpha;
            }
            *kept *= 1.0 - alpha;
            let mut j = if *n == k { k - 1 } else { *n };
            while j > 0 && key_less(t, index, out[j - 1].t, out[j - 1].index) {
                out[j] = out[j - 1];
                j -= 1;
            }
            out[j] = Hit { t, index, slot: (block * W + lane) as u32, alpha };
            hint(index);
            if *n < k {
                *n += 1;
            }
            if *n == k {
                *cull = cull.min(out[k - 1].t);
            }
            // Early termination: the hit where the (caller-order) product drops below the
            // cut-off is the last one composited; farther nodes need no visit. Every prefix
            // product is ≥ the whole set's, so while that stays clear of the cut-off (with
            // room for its rounding drift) no hit can be the one. Only a cull: skipping it
            // never changes which hits are composited.
            if stop_below > 0.0 && trans0 * *kept < stop_below * 1.01 {
                let mut tr = trans0;
                for h in &out[..*n] {
                    tr *= 1.0 - h.alpha;
                    if tr < stop_below {
                        *cull = cull.min(h.t);
                        break;
                    }
                }
            }
        }
    }

    /// Unit normal of the primitive in `slot` (a [`Hit`]'s slot).
    #[inline]
    pub(crate) fn slot_normal(&self, slot: u32) -> [f32; 3] {
        let (b, l) = (slot as usize / W, slot as usize % W);
        let p = &self.blocks[b];
        [p.normal[0][l], p.normal[1][l], p.normal[2][l]]
    }

    /// How a hit from behind (n·d > 0) on the primitive in `slot` composites: None when back
    /// faces are culled, else Some(dark) — dark ones occlude but carry no payload. One-sided,
    /// a back occluder is dark and any other back face hit is a grazing one (not dark).
    #[inline]
    pub(crate) fn back_face(&self, slot: u32) -> Option<bool> {
        if self.settings.two_sided {
            return Some(self.settings.dark_back_faces);
        }
        let (b, l) = (slot as usize / W, slot as usize % W);
        if self.blocks[b].back_lanes & (1 << l) != 0 {
            Some(true)
        } else {
            (self.settings.grazing_sin > 0.0).then_some(false)
        }
    }

    /// Plain closest-hit traversal (nearest valid hit beyond t_min): the benchmark's baseline.
    pub fn closest_hit(&self, origin: [f32; 3], dir: [f32; 3]) -> Option<(f32, u32)> {
        let r = PreparedRay::new(origin, dir);
        let mut out = [Hit::default(); MAX_CHUNK];
        let n = self.gather(&r, (f32::NEG_INFINITY, 0), 1, (1.0, 0.0), &mut out, &|_| {});
        (n == 1).then(|| (out[0].t, out[0].index))
    }
}

#[cfg(test)]
mod tests {
    use super::{MaybeUninit, W, WIDE_STACK, WideStack, angle_of, ord_bits, push_children, stack_entry};
    use rand::{RngExt, SeedableRng};
    use wide::f32x8;

    #[test]
    fn ordered_bits_keep_the_order_of_distances() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let special = [f32::NEG_INFINITY, -1e30, -1.0, -1e-30, -0.0, 0.0, 1e-30, 1e-4, 1.0, 1e30, f32::INFINITY];
        let mut xs: Vec<f32> = special.to_vec();
        xs.extend((0..2000).map(|_| rng.random_range(-10.0..10.0f32) * 10f32.powi(rng.random_range(-20..20))));
        for &a in &xs {
            for &b in &xs[..special.len()] {
                if a != b {
                    assert_eq!(a < b, ord_bits(a) < ord_bits(b), "{a} vs {b}");
                }
                assert!(ord_bits(a) != 0);
            }
        }
        assert!(ord_bits(-0.0) < ord_bits(0.0));
    }

    /// Against a plain sort: the nearest comes back, the others sit on the stack farthest
    /// first, nothing else moves; one or no child pushes nothing.
    #[test]
    fn pushed_children_pop_near_to_far() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
        for case in 0..20000 {
            let ties = case % 3 == 0;
            let t: [f32; W] = std::array::from_fn(|_| {
                if ties { rng.random_range(0..3) as f32 * 0.5 } else { rng.random_range(-1.0..50.0f32) }
            });
            let child: [u32; W] = std::array::from_fn(|j| 1 + j as u32 * 7 + if j % 2 == 0 { 1 << 31 } else { 0 });
            let mask: u32 = rng.random_range(0..256);
            let sp0 = rng.random_range(0..20usize);
            let mut stack: WideStack = [MaybeUninit::new(u64::MAX - 1); WIDE_STACK];
            let (sp, next) = push_children(&mut stack, sp0, f32x8::from(t), &child, mask);
            let mut want: Vec<u64> =
                (0..W).filter(|&j| mask >> j & 1 == 1).map(|j| stack_entry(child[j], t[j])).collect();
            want.sort_unstable();
            if want.is_empty() {
                assert_eq!((sp, next), (sp0, 0));
                continue;
            }
            assert_eq!(next, want[0], "mask {mask:08b} t {t:?}");
            assert_eq!(sp, sp0 + want.len() - 1);
            // SAFETY: the whole stack was initialised above.
            let got: Vec<u64> = (sp0..sp).map(|q| unsafe { stack[q].assume_init() }).collect();
            let far_first: Vec<u64> = want[1..].iter().rev().copied().collect();
            assert_eq!(got, far_first, "mask {mask:08b} t {t:?}");
            assert!((0..sp0).all(|q| unsafe { stack[q].assume_init() } == u64::MAX - 1));
        }
    }

    #[test]
    fn angle_of_bounds_acos_from_above_tightly() {
        for k in 0..=20000 {
            let c = -1.0 + 2.0 * k as f64 / 20000.0;
            let exact = c.acos();
            let bound = angle_of(c as f32) as f64;
            assert!(bound >= exact, "cos {c}: {bound} < acos {exact}");
            assert!(bound - exact < 2e-4, "cos {c}: {bound} is loose against {exact}");
        }
        assert!(angle_of(1.5) >= 0.0 && angle_of(-1.5) >= std::f64::consts::PI as f32 - 1e-6);
    }
}
