//! The BVH for scenes of up to [`WIDE_MAX_PRIMS`] primitives: an 8-wide BVH whose nodes keep
//! their children's boxes in SoA and whose leaves are **packets** of up to 8 triangles in SoA,
//! so that one box test or one triangle test covers 8 children or triangles at once (AVX2
//! intrinsics when the build targets AVX2 — x86-64-v3, `.cargo/config.toml` — else the same
//! arithmetic as plain lane loops).
//!
//! Why: the test scenes (the Cornell box: 36 triangles, the many-lights room: ~170) are tiny;
//! there obvhs' compressed CWBVH spends most of a ray in node decoding. `benches/bvh.rs` with
//! `BVH_BENCH_KIND` shows this BVH at least as fast as the CWBVH from 1K to 1M triangles too;
//! above [`WIDE_MAX_PRIMS`] the CWBVH is kept all the same (faster, parallel-friendly build).
//!
//! Contract (same as [`super::Accel`]):
//! - the triangle test is the watertight test of [`super::intersect_prim`], evaluated lane by
//!   lane with the same operations in the same order, so a packet lane returns bit-for-bit what
//!   the scalar test returns for that triangle (including the f64 fallback on exact zeros);
//! - box tests are conservative: the exit distance is scaled up by `1 + 2γ₃` (Ize 2013,
//!   "Robust BVH ray traversal"), zero direction components use a huge finite reciprocal
//!   (no `0 · ∞`), so a triangle on a box face is never culled by rounding;
//! - spheres are leaves of their own, intersected by [`super::intersect_sphere`];
//! - the closest hit is found with ordered (near-first) traversal; [`WideBvh::occluded`]
//!   stops at the first hit.
//!
//! Build: top-down binned SAH (16 bins per axis on centroids). Each node takes up to 8
//! clusters obtained by repeatedly splitting its largest cluster; a cluster of ≤ 8 triangles
//! (or one sphere) becomes a leaf, and leaf clusters are split further only while slots are
//! free and the split shrinks the summed box area (fewer packet tests per ray). From binary
//! depth [`MEDIAN_DEPTH`] on, splits are object medians, which bounds the depth; a tree whose
//! traversal could need more than [`STACK`] stack entries is not used (the caller builds the
//! CWBVH instead), so traversal needs no heap and no overflow checks beyond slice bounds.

use glam::Vec3;

use super::{Prim, RayShear, SPHERE_BIT, intersect_sphere};

/// Lanes of a node or packet.
pub(super) const LANES: usize = 8;
/// Largest primitive count for which [`super::AccelKind::Auto`] picks this BVH.
pub const WIDE_MAX_PRIMS: usize = 1 << 16;
/// From this binary split depth on, splits are object medians (bounded depth).
const MEDIAN_DEPTH: u32 = 24;
/// Traversal stack entries. The build computes the most a traversal can need and gives up
/// (the caller falls back to the CWBVH) when a tree would need more.
const STACK: usize = 64;
/// SAH bins per axis.
const BINS: usize = 16;
/// Ize's `1 + 2γ₃` with `γ₃ = 3u / (1 − 3u)`, `u = 2⁻²⁴`.
const TFAR_SCALE: f32 = 1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// Child reference tags (top two bits) and the empty slot.
const TAG_SHIFT: u32 = 30;
const TAG_INNER: u32 = 0;
const TAG_PACKET: u32 = 1;
const TAG_SPHERE: u32 = 2;
/// An inner node whose children are all leaves (packets or spheres): traversal handles its
/// children in place, nearest first, without pushing them (see [`WideBvh::intersect`]).
const TAG_LEAVES: u32 = 3;
const INDEX_MASK: u32 = (1 << TAG_SHIFT) - 1;
const EMPTY: u32 = u32::MAX;

/// Eight floats, one per lane.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct F8([f32; LANES]);

/// An inner node: the boxes of up to 8 children (empty slots have `min = +∞`, `max = −∞`).
#[derive(Clone, Debug)]
struct Node {
    /// Box minima per axis.
    min: [F8; 3],
    /// Box maxima per axis.
    max: [F8; 3],
    /// Child references (tagged), [`EMPTY`] for unused slots.
    child: [u32; LANES],
}

/// Up to 8 triangles; unused lanes hold NaN vertices, which never pass the test.
#[derive(Clone, Debug)]
struct Packet {
    /// `v[vertex][axis]`.
    v: [[F8; 3]; 3],
    /// Index into the accel's primitive list per lane.
    prim: [u32; LANES],
}

/// The 8-wide BVH (see the module docs).
#[derive(Clone, Debug)]
pub(super) struct WideBvh {
    nodes: Vec<Node>,
    packets: Vec<Packet>,
    /// Tagged reference of the root (a leaf when the scene fits in one).
    root: u32,
    /// The root is a [`TAG_LEAVES`] node whose children are all packets (no spheres): the
    /// one-node paths then skip the leaf tag test, and the sphere test's per-ray set-up,
    /// which LLVM hoists out of the leaf loop, is not paid by scenes without spheres.
    packets_only_root: bool,
}

/// A hit found by traversal: primitive index, `t` and barycentrics `(b1, b2)`.
pub(super) type WideHit = (u32, f32, f32, f32);

/// The closest hit so far during traversal.
#[derive(Clone, Copy, Debug)]
struct Closest {
    /// `t` of the hit, else the ray's `t_max`.
    t: f32,
    /// Primitive index of the hit, [`NO_PRIM`] for none.
    prim: u32,
    /// Barycentric `b1` of the hit.
    b1: f32,
    /// Barycentric `b2` of the hit.
    b2: f32,
}

/// [`Closest::prim`] before any hit (primitive indices stay below [`WIDE_MAX_PRIMS`]).
const NO_PRIM: u32 = u32::MAX;

impl Closest {
    /// Takes a packet's closest hit, if it has one (then nearer than `self.t`: the packet was
    /// tested against it).
    #[inline(always)]
    fn merge(&mut self, c: PacketClosest) {
        if c.hit {
            *self = Closest {
                t: c.t,
                prim: c.prim,
                b1: c.b1,
                b2: c.b2,
            };
        }
    }

    /// The hit, if any.
    #[inline(always)]
    fn hit(self) -> Option<WideHit> {
        (self.prim != NO_PRIM).then_some((self.prim, self.t, self.b1, self.b2))
    }
}

/// A primitive during the build.
#[derive(Clone, Copy, Debug)]
struct Item {
    lo: Vec3,
    hi: Vec3,
    centroid: Vec3,
    prim: u32,
    sphere: bool,
}

/// Surface area of a box (0 for an empty box).
#[inline]
fn area(lo: Vec3, hi: Vec3) -> f32 {
    let e = (hi - lo).max(Vec3::ZERO);
    2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
}

fn bounds(items: &[Item]) -> (Vec3, Vec3) {
    items.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), it| (lo.min(it.lo), hi.max(it.hi)),
    )
}

/// Whether a cluster may be a leaf: ≤ 8 triangles, or exactly one sphere.
fn leafable(items: &[Item]) -> bool {
    items.len() == 1 || (items.len() <= LANES && items.iter().all(|it| !it.sphere))
}

impl WideBvh {
    /// Builds the BVH over `prims` (lanes and leaves refer to `prims` by index).
    pub(super) fn new(prims: &[Prim]) -> Option<Self> {
        let mut items: Vec<Item> = prims
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let (lo, hi) = if p.shape & SPHERE_BIT != 0 {
                    let r = Vec3::splat(p.b.x.abs());
                    (p.a - r, p.a + r)
                } else {
                    (p.a.min(p.b).min(p.c), p.a.max(p.b).max(p.c))
                };
                Item {
                    lo,
                    hi,
                    centroid: 0.5 * (lo + hi),
                    prim: i as u32,
                    sphere: p.shape & SPHERE_BIT != 0,
                }
            })
            .collect();
        if items.is_empty() {
            return None;
        }
        let mut bvh = WideBvh {
            nodes: Vec::new(),
            packets: Vec::new(),
            root: EMPTY,
            packets_only_root: false,
        };
        let (root, need) = bvh.build(prims, &mut items, 0);
        bvh.root = root;
        bvh.packets_only_root = root >> TAG_SHIFT == TAG_LEAVES
            && bvh.nodes[(root & INDEX_MASK) as usize]
                .child
                .iter()
                .all(|&c| c == EMPTY || c >> TAG_SHIFT == TAG_PACKET);
        // `need` entries above the root's own slot: the fixed-size stacks must hold them.
        (need < STACK).then_some(bvh)
    }

    /// Builds the subtree of `items` and returns its tagged reference and the traversal stack
    /// entries it may need beyond its own: an inner node with `k` children pushes `k` after
    /// being popped, and any child may be processed first, so `k − 1 + max(child need)`.
    fn build(&mut self, prims: &[Prim], items: &mut [Item], depth: u32) -> (u32, usize) {
        if leafable(items) {
            return (self.leaf(prims, items), 0);
        }
        // Clusters as ranges of `items`, split until 8 or nothing worth splitting.
        let mut clusters: Vec<(usize, usize)> = vec![(0, items.len())];
        loop {
            if clusters.len() == LANES {
                break;
            }
            // Prefer splitting clusters that cannot be leaves (largest area first); then
            // leaf clusters whose split shrinks the summed area.
            let mut pick = None;
            let mut pick_area = f32::NEG_INFINITY;
            for (k, &(s, e)) in clusters.iter().enumerate() {
                if !leafable(&items[s..e]) {
                    let (lo, hi) = bounds(&items[s..e]);
                    let a = area(lo, hi);
                    if a > pick_area {
                        pick_area = a;
                        pick = Some(k);
                    }
                }
            }
            let k = match pick {
                Some(k) => k,
                None => {
                    // All leaves: split the one whose split gains most, if any gains.
                    let mut best = None;
                    let mut best_gain = 0.0f32;
                    for (k, &(s, e)) in clusters.iter().enumerate() {
                        if e - s < 2 {
                            continue;
                        }
                        let (lo, hi) = bounds(&items[s..e]);
                        let a = area(lo, hi);
                        let mut trial = items[s..e].to_vec();
                        let m = split(&mut trial, depth);
                        let (l0, h0) = bounds(&trial[..m]);
                        let (l1, h1) = bounds(&trial[m..]);
                        let gain = a - (area(l0, h0) + area(l1, h1));
                        if gain > 0.1 * a && gain > best_gain {
                            best_gain = gain;
                            best = Some(k);
                        }
                    }
                    match best {
                        Some(k) => k,
                        None => break,
                    }
                }
            };
            let (s, e) = clusters[k];
            let m = s + split(&mut items[s..e], depth);
            clusters[k] = (s, m);
            clusters.push((m, e));
        }
        let index = self.nodes.len();
        self.nodes.push(Node {
            min: [F8([f32::INFINITY; LANES]); 3],
            max: [F8([f32::NEG_INFINITY; LANES]); 3],
            child: [EMPTY; LANES],
        });
        let mut need = 0;
        let mut leaves_only = true;
        for (lane, &(s, e)) in clusters.iter().enumerate() {
            let (lo, hi) = bounds(&items[s..e]);
            let (child, child_need) = self.build(prims, &mut items[s..e], depth + 1);
            need = need.max(child_need);
            leaves_only &= matches!(child >> TAG_SHIFT, TAG_PACKET | TAG_SPHERE);
            let node = &mut self.nodes[index];
            for axis in 0..3 {
                node.min[axis].0[lane] = lo[axis];
                node.max[axis].0[lane] = hi[axis];
            }
            node.child[lane] = child;
        }
        let tag = if leaves_only { TAG_LEAVES } else { TAG_INNER };
        // (The bound is kept for `TAG_LEAVES` nodes too, which push nothing: an overestimate,
        // so the choice between this BVH and the CWBVH stays what it was.)
        ((tag << TAG_SHIFT) | index as u32, clusters.len() - 1 + need)
    }

    /// A leaf for a leafable cluster.
    fn leaf(&mut self, prims: &[Prim], items: &[Item]) -> u32 {
        if items[0].sphere {
            return (TAG_SPHERE << TAG_SHIFT) | items[0].prim;
        }
        let mut packet = Packet {
            v: [[F8([f32::NAN; LANES]); 3]; 3],
            prim: [0; LANES],
        };
        for (lane, it) in items.iter().enumerate() {
            let p = &prims[it.prim as usize];
            for (vertex, pos) in [p.a, p.b, p.c].into_iter().enumerate() {
                for axis in 0..3 {
                    packet.v[vertex][axis].0[lane] = pos[axis];
                }
            }
            packet.prim[lane] = it.prim;
        }
        self.packets.push(packet);
        (TAG_PACKET << TAG_SHIFT) | (self.packets.len() - 1) as u32
    }

    /// Closest hit with `t ∈ (0, t_max)`.
    #[inline]
    pub(super) fn intersect(&self, prims: &[Prim], ray: &RayShear, t_max: f32) -> Option<WideHit> {
        let boxes = BoxRay::new(ray);
        let mut best = Closest {
            t: t_max,
            prim: NO_PRIM,
            b1: 0.0,
            b2: 0.0,
        };
        if self.root >> TAG_SHIFT == TAG_LEAVES {
            // A one-node tree (scenes the build packs into one node's 8 leaves, e.g. the
            // Cornell box): no stack at all.
            let node = &self.nodes[(self.root & INDEX_MASK) as usize];
            if self.packets_only_root {
                self.leaves_closest::<false>(prims, node, &boxes, ray, &mut best);
            } else {
                self.leaves_closest::<true>(prims, node, &boxes, ray, &mut best);
            }
            return best.hit();
        }
        // Uninitialised: only entries below `sp` are read (zeroing 512 bytes per ray cost ~3 %
        // of all instructions).
        let mut stack = [std::mem::MaybeUninit::<(u32, f32)>::uninit(); STACK];
        stack[0].write((self.root, 0.0));
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            // SAFETY: entries below `sp` were written (pushes write before incrementing `sp`).
            let (r, t_near) = unsafe { stack[sp].assume_init() };
            if t_near > best.t {
                continue;
            }
            let index = (r & INDEX_MASK) as usize;
            match r >> TAG_SHIFT {
                TAG_INNER => {
                    let node = &self.nodes[index];
                    let (mask, t_in) = boxes.test(node, best.t);
                    // Push the hit children sorted by descending entry distance (insertion
                    // into the stack top) so that the nearest is popped first. Cannot
                    // overflow: the build checked the tree's stack need (see STACK).
                    let base = sp;
                    let mut m = mask;
                    while m != 0 {
                        let lane = m.trailing_zeros() as usize;
                        m &= m - 1;
                        let entry = (node.child[lane], t_in[lane]);
                        let mut j = sp;
                        // SAFETY: `base ≤ j − 1 < sp`: a written entry.
                        while j > base && unsafe { stack[j - 1].assume_init().1 } < entry.1 {
                            stack[j] = stack[j - 1];
                            j -= 1;
                        }
                        stack[j].write(entry);
                        sp += 1;
                    }
                }
                TAG_LEAVES => {
                    self.leaves_closest::<true>(prims, &self.nodes[index], &boxes, ray, &mut best);
                }
                _ => self.leaf_closest::<true>(prims, r, ray, &mut best),
            }
        }
        best.hit()
    }

    /// The closest-hit test of a [`TAG_LEAVES`] node's children. The stack path would push
    /// them sorted and pop them at once, nearest first (equal entry distances: higher lane
    /// first), skipping those entered beyond the closest hit so far. Same order and same skips
    /// here, without the stack.
    /// `SPHERES = false`: every child is a packet (see [`WideBvh::packets_only_root`]).
    #[inline(always)]
    fn leaves_closest<const SPHERES: bool>(
        &self,
        prims: &[Prim],
        node: &Node,
        boxes: &BoxRay,
        ray: &RayShear,
        best: &mut Closest,
    ) {
        let (mut mask, t_in) = boxes.test(node, best.t);
        while mask != 0 {
            // A single candidate left (often the last one): no lane minimum needed.
            let lane = if mask & (mask - 1) == 0 {
                mask.trailing_zeros() as usize
            } else {
                nearest_lane(&t_in, mask)
            };
            if t_in[lane] > best.t {
                break;
            }
            mask &= !(1 << lane);
            self.leaf_closest::<SPHERES>(prims, node.child[lane], ray, best);
        }
    }

    /// The closest-hit test of leaf `r` (a packet or sphere reference): updates `best` when it
    /// has a hit nearer than `best.t`. `SPHERES = false`: `r` is known to be a packet.
    #[inline(always)]
    fn leaf_closest<const SPHERES: bool>(
        &self,
        prims: &[Prim],
        r: u32,
        ray: &RayShear,
        best: &mut Closest,
    ) {
        let index = (r & INDEX_MASK) as usize;
        if !SPHERES || r >> TAG_SHIFT == TAG_PACKET {
            best.merge(packet_closest(&self.packets[index], ray, best.t));
        } else {
            let p = &prims[index];
            if let Some(t) = intersect_sphere(p.a, p.b.x, ray.o, ray.d, best.t) {
                *best = Closest {
                    t,
                    prim: index as u32,
                    b1: 0.0,
                    b2: 0.0,
                };
            }
        }
    }

    /// The any-hit test of a [`TAG_LEAVES`] node's children, tested in place in the order the
    /// stack would pop them (highest lane first).
    /// `SPHERES = false`: every child is a packet (see [`WideBvh::packets_only_root`]).
    #[inline(always)]
    fn leaves_any<const SPHERES: bool>(
        &self,
        prims: &[Prim],
        node: &Node,
        boxes: &BoxRay,
        ray: &RayShear,
        t_max: f32,
    ) -> bool {
        let (mut mask, _) = boxes.test(node, t_max);
        while mask != 0 {
            let lane = 31 - mask.leading_zeros() as usize;
            mask &= !(1 << lane);
            if self.leaf_any::<SPHERES>(prims, node.child[lane], ray, t_max) {
                return true;
            }
        }
        false
    }

    /// The any-hit test of leaf `r` (a packet or sphere reference; a packet when `!SPHERES`).
    #[inline(always)]
    fn leaf_any<const SPHERES: bool>(
        &self,
        prims: &[Prim],
        r: u32,
        ray: &RayShear,
        t_max: f32,
    ) -> bool {
        let index = (r & INDEX_MASK) as usize;
        if !SPHERES || r >> TAG_SHIFT == TAG_PACKET {
            packet_any(&self.packets[index], ray, t_max)
        } else {
            let p = &prims[index];
            intersect_sphere(p.a, p.b.x, ray.o, ray.d, t_max).is_some()
        }
    }

    /// Whether anything is hit with `t ∈ (0, t_max)`.
    #[inline]
    pub(super) fn occluded(&self, prims: &[Prim], ray: &RayShear, t_max: f32) -> bool {
        let boxes = BoxRay::new(ray);
        if self.root >> TAG_SHIFT == TAG_LEAVES {
            // A one-node tree: no stack (as in `intersect`).
            let node = &self.nodes[(self.root & INDEX_MASK) as usize];
            return if self.packets_only_root {
                self.leaves_any::<false>(prims, node, &boxes, ray, t_max)
            } else {
                self.leaves_any::<true>(prims, node, &boxes, ray, t_max)
            };
        }
        let mut stack = [std::mem::MaybeUninit::<u32>::uninit(); STACK];
        stack[0].write(self.root);
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            // SAFETY: entries below `sp` were written (pushes write before incrementing `sp`).
            let r = unsafe { stack[sp].assume_init() };
            let index = (r & INDEX_MASK) as usize;
            match r >> TAG_SHIFT {
                TAG_INNER => {
                    let node = &self.nodes[index];
                    let (mask, _) = boxes.test(node, t_max);
                    let mut m = mask;
                    while m != 0 {
                        let lane = m.trailing_zeros() as usize;
                        m &= m - 1;
                        stack[sp].write(node.child[lane]);
                        sp += 1;
                    }
                }
                TAG_LEAVES => {
                    if self.leaves_any::<true>(prims, &self.nodes[index], &boxes, ray, t_max) {
                        return true;
                    }
                }
                _ => {
                    if self.leaf_any::<true>(prims, r, ray, t_max) {
                        return true;
                    }
                }
            }
        }
        false
    }
}

/// Splits `items` in two non-empty parts (reordering it) and returns the size of the first:
/// binned SAH on centroids, or the object median along the widest centroid axis when the
/// SAH finds no split or below [`MEDIAN_DEPTH`].
fn split(items: &mut [Item], depth: u32) -> usize {
    let n = items.len();
    let (clo, chi) = items.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), it| (lo.min(it.centroid), hi.max(it.centroid)),
    );
    let extent = chi - clo;
    if depth < MEDIAN_DEPTH {
        let mut best: Option<(f32, usize, usize)> = None; // (cost, axis, first right bin)
        for axis in 0..3 {
            if extent[axis].is_nan() || extent[axis] <= 0.0 {
                continue;
            }
            let scale = BINS as f32 / extent[axis];
            let bin_of = |c: f32| (((c - clo[axis]) * scale) as usize).min(BINS - 1);
            let mut count = [0usize; BINS];
            let mut blo = [Vec3::splat(f32::INFINITY); BINS];
            let mut bhi = [Vec3::splat(f32::NEG_INFINITY); BINS];
            for it in items.iter() {
                let b = bin_of(it.centroid[axis]);
                count[b] += 1;
                blo[b] = blo[b].min(it.lo);
                bhi[b] = bhi[b].max(it.hi);
            }
            // Sweep: left areas/counts for planes after bin i.
            let mut left = [(0.0f32, 0usize); BINS];
            let (mut lo, mut hi, mut c) = (
                Vec3::splat(f32::INFINITY),
                Vec3::splat(f32::NEG_INFINITY),
                0,
            );
            for i in 0..BINS - 1 {
                lo = lo.min(blo[i]);
                hi = hi.max(bhi[i]);
                c += count[i];
                left[i] = (area(lo, hi), c);
            }
            let (mut lo, mut hi, mut c) = (
                Vec3::splat(f32::INFINITY),
                Vec3::splat(f32::NEG_INFINITY),
                0,
            );
            for i in (1..BINS).rev() {
                lo = lo.min(blo[i]);
                hi = hi.max(bhi[i]);
                c += count[i];
                let (al, cl) = left[i - 1];
                if cl == 0 || c == 0 {
                    continue;
                }
                let cost = al * cl as f32 + area(lo, hi) * c as f32;
                if best.is_none_or(|(bc, _, _)| cost < bc) {
                    best = Some((cost, axis, i));
                }
            }
        }
        if let Some((_, axis, bin_plane)) = best {
            let scale = BINS as f32 / extent[axis];
            let mut m = 0;
            for i in 0..n {
                let b = (((items[i].centroid[axis] - clo[axis]) * scale) as usize).min(BINS - 1);
                if b < bin_plane {
                    items.swap(i, m);
                    m += 1;
                }
            }
            if m > 0 && m < n {
                return m;
            }
        }
    }
    // Object median along the widest centroid axis (also for coincident centroids).
    let axis = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    let m = n / 2;
    items.select_nth_unstable_by(m, |a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
    m
}

/// Per-ray constants of the 8-wide box test.
struct BoxRay {
    /// Origin per axis.
    o: [f32; 3],
    /// Reciprocal direction per axis (a huge finite value for zero components).
    inv: [f32; 3],
    /// Whether the direction component is negative (then entry is at the box maximum).
    neg: [bool; 3],
}

impl BoxRay {
    #[inline(always)]
    fn new(ray: &RayShear) -> Self {
        Self {
            o: ray.o.to_array(),
            inv: ray.inv_d.to_array(),
            neg: ray.d.to_array().map(|d| d < 0.0),
        }
    }

    /// Lane mask of the children whose box the ray enters before `t_max`, and the entry
    /// distances (AVX2 when the build target has it, else [`Self::test_portable`]).
    #[inline(always)]
    fn test(&self, node: &Node, t_max: f32) -> (u32, [f32; LANES]) {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        {
            avx2::node_test(self, node, t_max)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            self.test_portable(node, t_max)
        }
    }

    /// [`Self::test`] as plain lane loops.
    #[cfg_attr(all(target_arch = "x86_64", target_feature = "avx2"), allow(dead_code))]
    #[inline(always)]
    fn test_portable(&self, node: &Node, t_max: f32) -> (u32, [f32; LANES]) {
        let mut t_in = [0.0f32; LANES];
        let mut t_out = [t_max; LANES];
        for axis in 0..3 {
            let (near, far) = if self.neg[axis] {
                (&node.max[axis].0, &node.min[axis].0)
            } else {
                (&node.min[axis].0, &node.max[axis].0)
            };
            let (o, inv) = (self.o[axis], self.inv[axis]);
            for l in 0..LANES {
                let a = (near[l] - o) * inv;
                let b = (far[l] - o) * inv;
                t_in[l] = if a > t_in[l] { a } else { t_in[l] };
                t_out[l] = if b < t_out[l] { b } else { t_out[l] };
            }
        }
        let mut mask = 0u32;
        for l in 0..LANES {
            mask |= u32::from(t_in[l] <= t_out[l] * TFAR_SCALE) << l;
        }
        (mask, t_in)
    }
}

/// The lane of `mask` (non-zero) with the smallest `t_in`; among equal ones the highest lane
/// (the order in which the traversal stack pops children pushed in lane order). AVX2 when the
/// build target has it, else [`nearest_lane_portable`].
#[inline(always)]
fn nearest_lane(t_in: &[f32; LANES], mask: u32) -> usize {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    {
        avx2::nearest_lane(t_in, mask)
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        nearest_lane_portable(t_in, mask)
    }
}

/// [`nearest_lane`] as a lane loop.
#[cfg_attr(all(target_arch = "x86_64", target_feature = "avx2"), allow(dead_code))]
#[inline(always)]
fn nearest_lane_portable(t_in: &[f32; LANES], mask: u32) -> usize {
    let mut lane = 0;
    let mut t = f32::INFINITY;
    let mut found = false;
    for (l, &tl) in t_in.iter().enumerate() {
        if mask >> l & 1 != 0 && (!found || tl <= t) {
            (lane, t, found) = (l, tl, true);
        }
    }
    lane
}

/// Result of a packet test: mask of lanes hit with `t ∈ (0, t_max)`, then `t`, `b1`, `b2` per
/// lane (meaningful in the masked lanes only).
type PacketHits = (u32, [f32; LANES], [f32; LANES], [f32; LANES]);

/// The watertight test of [`super::intersect_prim`] on 8 lanes (AVX2 when the build target
/// has it, else [`packet_test_portable`]).
#[inline(always)]
fn packet_test(p: &Packet, ray: &RayShear, t_max: f32) -> PacketHits {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    {
        avx2::packet_test(p, ray, t_max)
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        packet_test_portable(p, ray, t_max)
    }
}

/// [`packet_test`] as plain lane loops.
#[cfg_attr(all(target_arch = "x86_64", target_feature = "avx2"), allow(dead_code))]
#[inline(always)]
fn packet_test_portable(p: &Packet, ray: &RayShear, t_max: f32) -> PacketHits {
    let [kx, ky, kz] = ray.k;
    let (ox, oy, oz) = (ray.o_perm.x, ray.o_perm.y, ray.o_perm.z);
    let (sx, sy, sz) = (ray.s.x, ray.s.y, ray.s.z);
    // Sheared vertex coordinates relative to the origin, per vertex.
    let mut x = [[0.0f32; LANES]; 3];
    let mut y = [[0.0f32; LANES]; 3];
    let mut z = [[0.0f32; LANES]; 3];
    for v in 0..3 {
        let (px, py, pz) = (&p.v[v][kx].0, &p.v[v][ky].0, &p.v[v][kz].0);
        for l in 0..LANES {
            let (ax, ay, az) = (px[l] - ox, py[l] - oy, pz[l] - oz);
            x[v][l] = ax - sx * az;
            y[v][l] = ay - sy * az;
            z[v][l] = sz * az;
        }
    }
    let [ax, bx, cx] = x;
    let [ay, by, cy] = y;
    let mut u = [0.0f32; LANES];
    let mut v = [0.0f32; LANES];
    let mut w = [0.0f32; LANES];
    let mut zero = 0u32;
    for l in 0..LANES {
        u[l] = cx[l] * by[l] - cy[l] * bx[l];
        v[l] = ax[l] * cy[l] - ay[l] * cx[l];
        w[l] = bx[l] * ay[l] - by[l] * ax[l];
        zero |= u32::from(u[l] == 0.0 || v[l] == 0.0 || w[l] == 0.0) << l;
    }
    while zero != 0 {
        let l = zero.trailing_zeros() as usize;
        zero &= zero - 1;
        u[l] = edge_f64(cx[l], by[l], cy[l], bx[l]);
        v[l] = edge_f64(ax[l], cy[l], ay[l], cx[l]);
        w[l] = edge_f64(bx[l], ay[l], by[l], ax[l]);
    }
    let mut t = [0.0f32; LANES];
    let mut b1 = [0.0f32; LANES];
    let mut b2 = [0.0f32; LANES];
    let mut mask = 0u32;
    for l in 0..LANES {
        let inside = (u[l] >= 0.0 && v[l] >= 0.0 && w[l] >= 0.0)
            || (u[l] <= 0.0 && v[l] <= 0.0 && w[l] <= 0.0);
        let det = u[l] + v[l] + w[l];
        let t_scaled = u[l] * z[0][l] + v[l] * z[1][l] + w[l] * z[2][l];
        let inv_det = 1.0 / det;
        t[l] = t_scaled * inv_det;
        b1[l] = v[l] * inv_det;
        b2[l] = w[l] * inv_det;
        let ok = inside && det != 0.0 && t[l] > 0.0 && t[l] < t_max;
        mask |= u32::from(ok) << l;
    }
    (mask, t, b1, b2)
}

/// The closest triangle of a packet with `t < t_max` (see [`packet_closest`]).
#[derive(Clone, Copy, Debug)]
struct PacketClosest {
    /// Whether any lane was hit; the other fields are meaningful only then.
    hit: bool,
    /// The hit's `t` (`+∞` when nothing was hit).
    t: f32,
    /// Primitive index.
    prim: u32,
    /// Barycentric `b1`.
    b1: f32,
    /// Barycentric `b2`.
    b2: f32,
}

/// Closest triangle of a packet with `t < t_max`; of equal `t`, the lowest lane (AVX2 when
/// the build target has it, else [`packet_closest_portable`]).
#[inline(always)]
fn packet_closest(p: &Packet, ray: &RayShear, t_max: f32) -> PacketClosest {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    {
        avx2::packet_closest(p, ray, t_max)
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        packet_closest_portable(p, ray, t_max)
    }
}

/// [`packet_closest`] as a lane loop.
#[cfg_attr(all(target_arch = "x86_64", target_feature = "avx2"), allow(dead_code))]
#[inline(always)]
fn packet_closest_portable(p: &Packet, ray: &RayShear, t_max: f32) -> PacketClosest {
    let (mut mask, t, b1, b2) = packet_test(p, ray, t_max);
    let mut best = PacketClosest {
        hit: false,
        t: f32::INFINITY,
        prim: 0,
        b1: 0.0,
        b2: 0.0,
    };
    while mask != 0 {
        let l = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        if t[l] < best.t {
            best = PacketClosest {
                hit: true,
                t: t[l],
                prim: p.prim[l],
                b1: b1[l],
                b2: b2[l],
            };
        }
    }
    best
}

/// Whether any triangle of a packet is hit with `t < t_max`.
#[inline(always)]
fn packet_any(p: &Packet, ray: &RayShear, t_max: f32) -> bool {
    packet_test(p, ray, t_max).0 != 0
}

/// Exactly-zero edge functions in f32: decide in f64 so neighbours agree (as the scalar test).
#[inline]
fn edge_f64(p: f32, q: f32, r: f32, s: f32) -> f32 {
    (f64::from(p) * f64::from(q) - f64::from(r) * f64::from(s)) as f32
}

/// AVX2 versions of the lane loops: the same operations in the same order (no FMA
/// contraction in the triangle test, so lanes equal the scalar test bit for bit).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{
        BoxRay, F8, LANES, Node, Packet, PacketClosest, PacketHits, RayShear, TFAR_SCALE, edge_f64,
    };

    #[inline(always)]
    fn load(v: &F8) -> __m256 {
        // SAFETY: AVX2 is enabled for the whole build (cfg); `F8` is 8 floats aligned to 32
        // bytes.
        unsafe { _mm256_load_ps(v.0.as_ptr()) }
    }

    #[inline(always)]
    fn store(v: __m256) -> [f32; LANES] {
        let mut out = F8([0.0; LANES]);
        // SAFETY: as in `load`.
        unsafe { _mm256_store_ps(out.0.as_mut_ptr(), v) };
        out.0
    }

    /// [`super::nearest_lane`]: the masked lanes' minimum by three lane-swapping `min`s, then
    /// the highest masked lane equal to it. Entry distances are never NaN (`maxps` with the
    /// initial 0 keeps the non-NaN operand), so the minimum equals one of the masked lanes.
    #[inline(always)]
    pub(super) fn nearest_lane(t_in: &[f32; LANES], mask: u32) -> usize {
        // SAFETY: AVX2 is enabled for the whole build (cfg): the intrinsics are available.
        unsafe {
            let bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let live =
                _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32(mask as i32), bits), bits);
            let t = _mm256_blendv_ps(
                _mm256_set1_ps(f32::INFINITY),
                _mm256_loadu_ps(t_in.as_ptr()),
                _mm256_castsi256_ps(live),
            );
            let m = _mm256_min_ps(t, _mm256_permute2f128_ps::<1>(t, t));
            let m = _mm256_min_ps(m, _mm256_permute_ps::<0b01_00_11_10>(m));
            let m = _mm256_min_ps(m, _mm256_permute_ps::<0b10_11_00_01>(m));
            let eq = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(t, m)) as u32 & mask;
            31 - eq.leading_zeros() as usize
        }
    }

    #[inline(always)]
    pub(super) fn node_test(b: &BoxRay, node: &Node, t_max: f32) -> (u32, [f32; LANES]) {
        // SAFETY: AVX2 is enabled for the whole build (cfg): the intrinsics are available.
        unsafe {
            let mut t_in = _mm256_setzero_ps();
            let mut t_out = _mm256_set1_ps(t_max);
            for axis in 0..3 {
                let (near, far) = if b.neg[axis] {
                    (&node.max[axis], &node.min[axis])
                } else {
                    (&node.min[axis], &node.max[axis])
                };
                let o = _mm256_set1_ps(b.o[axis]);
                let inv = _mm256_set1_ps(b.inv[axis]);
                let a = _mm256_mul_ps(_mm256_sub_ps(load(near), o), inv);
                let f = _mm256_mul_ps(_mm256_sub_ps(load(far), o), inv);
                // maxps(a, b) = a > b ? a : b, as the portable loop.
                t_in = _mm256_max_ps(a, t_in);
                t_out = _mm256_min_ps(f, t_out);
            }
            let t_out = _mm256_mul_ps(t_out, _mm256_set1_ps(TFAR_SCALE));
            let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(t_in, t_out)) as u32;
            (mask, store(t_in))
        }
    }

    /// The packet test as vectors: lanes hit (the sign bits of the first; its other bits are
    /// meaningless), `t`, `v`, `w` and `1 / det` per lane.
    #[inline(always)]
    fn packet_lanes(
        p: &Packet,
        ray: &RayShear,
        t_max: f32,
    ) -> (__m256, __m256, __m256, __m256, __m256) {
        // SAFETY: AVX2 is enabled for the whole build (cfg): the intrinsics are available.
        unsafe {
            let [kx, ky, kz] = ray.k;
            let (ox, oy, oz) = (
                _mm256_set1_ps(ray.o_perm.x),
                _mm256_set1_ps(ray.o_perm.y),
                _mm256_set1_ps(ray.o_perm.z),
            );
            let (sx, sy, sz) = (
                _mm256_set1_ps(ray.s.x),
                _mm256_set1_ps(ray.s.y),
                _mm256_set1_ps(ray.s.z),
            );
            let zero = _mm256_setzero_ps();
            let mut x = [zero; 3];
            let mut y = [zero; 3];
            let mut z = [zero; 3];
            for v in 0..3 {
                let ax = _mm256_sub_ps(load(&p.v[v][kx]), ox);
                let ay = _mm256_sub_ps(load(&p.v[v][ky]), oy);
                let az = _mm256_sub_ps(load(&p.v[v][kz]), oz);
                x[v] = _mm256_sub_ps(ax, _mm256_mul_ps(sx, az));
                y[v] = _mm256_sub_ps(ay, _mm256_mul_ps(sy, az));
                z[v] = _mm256_mul_ps(sz, az);
            }
            let [ax, bx, cx] = x;
            let [ay, by, cy] = y;
            let mut u = _mm256_sub_ps(_mm256_mul_ps(cx, by), _mm256_mul_ps(cy, bx));
            let mut v = _mm256_sub_ps(_mm256_mul_ps(ax, cy), _mm256_mul_ps(ay, cx));
            let mut w = _mm256_sub_ps(_mm256_mul_ps(bx, ay), _mm256_mul_ps(by, ax));
            let on_edge = _mm256_or_ps(
                _mm256_or_ps(
                    _mm256_cmp_ps::<_CMP_EQ_OQ>(u, zero),
                    _mm256_cmp_ps::<_CMP_EQ_OQ>(v, zero),
                ),
                _mm256_cmp_ps::<_CMP_EQ_OQ>(w, zero),
            );
            let mut fix = _mm256_movemask_ps(on_edge) as u32;
            // Sign bit set in the lanes that are *not* inside (other bits meaningless).
            let outside = if fix != 0 {
                let (ax, ay, bx, by, cx, cy) = (
                    store(ax),
                    store(ay),
                    store(bx),
                    store(by),
                    store(cx),
                    store(cy),
                );
                let (mut us, mut vs, mut ws) = (store(u), store(v), store(w));
                while fix != 0 {
                    let l = fix.trailing_zeros() as usize;
                    fix &= fix - 1;
                    us[l] = edge_f64(cx[l], by[l], cy[l], bx[l]);
                    vs[l] = edge_f64(ax[l], cy[l], ay[l], cx[l]);
                    ws[l] = edge_f64(bx[l], ay[l], by[l], ax[l]);
                }
                u = load(&F8(us));
                v = load(&F8(vs));
                w = load(&F8(ws));
                let all_ge = _mm256_and_ps(
                    _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_GE_OQ>(u, zero),
                        _mm256_cmp_ps::<_CMP_GE_OQ>(v, zero),
                    ),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(w, zero),
                );
                let all_le = _mm256_and_ps(
                    _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_LE_OQ>(u, zero),
                        _mm256_cmp_ps::<_CMP_LE_OQ>(v, zero),
                    ),
                    _mm256_cmp_ps::<_CMP_LE_OQ>(w, zero),
                );
                _mm256_xor_ps(
                    _mm256_or_ps(all_ge, all_le),
                    _mm256_castsi256_ps(_mm256_set1_epi32(-1)),
                )
            } else {
                // No edge function is ±0: for a non-NaN `x ≠ 0`, `x ≥ 0` ⇔ `x > 0` ⇔ sign
                // bit clear, so "all ≥ 0 or all ≤ 0" is "u, v, w have one sign" (sign bit of
                // `(u ^ v) | (u ^ w)` clear). A NaN lane fails `det ≠ 0` below either way.
                _mm256_or_ps(_mm256_xor_ps(u, v), _mm256_xor_ps(u, w))
            };
            let det = _mm256_add_ps(_mm256_add_ps(u, v), w);
            let t_scaled = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(u, z[0]), _mm256_mul_ps(v, z[1])),
                _mm256_mul_ps(w, z[2]),
            );
            let inv_det = _mm256_div_ps(_mm256_set1_ps(1.0), det);
            let t = _mm256_mul_ps(t_scaled, inv_det);
            // `!outside & rest`: the sign bit is the hit flag (`movemask`, `blendv` and
            // `vtestps` read only sign bits).
            let ok = _mm256_andnot_ps(
                outside,
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_NEQ_OQ>(det, zero),
                    _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_GT_OQ>(t, zero),
                        _mm256_cmp_ps::<_CMP_LT_OQ>(t, _mm256_set1_ps(t_max)),
                    ),
                ),
            );
            (ok, t, v, w, inv_det)
        }
    }

    #[inline(always)]
    pub(super) fn packet_test(p: &Packet, ray: &RayShear, t_max: f32) -> PacketHits {
        let (ok, t, v, w, inv_det) = packet_lanes(p, ray, t_max);
        // SAFETY: AVX2 is enabled for the whole build (cfg): the intrinsics are available.
        unsafe {
            let mask = _mm256_movemask_ps(ok) as u32;
            if mask == 0 {
                return (0, [0.0; LANES], [0.0; LANES], [0.0; LANES]);
            }
            (
                mask,
                store(t),
                store(_mm256_mul_ps(v, inv_det)),
                store(_mm256_mul_ps(w, inv_det)),
            )
        }
    }

    /// [`super::packet_closest`]: the hit lanes' smallest `t` by three lane-swapping `min`s,
    /// then the lowest hit lane holding it (no loop over the hit lanes).
    #[inline(always)]
    pub(super) fn packet_closest(p: &Packet, ray: &RayShear, t_max: f32) -> PacketClosest {
        let (ok, t, v, w, inv_det) = packet_lanes(p, ray, t_max);
        // SAFETY: AVX2 is enabled for the whole build (cfg): the intrinsics are available.
        unsafe {
            let mask = _mm256_movemask_ps(ok) as u32;
            if mask == 0 {
                // No hit: skip the lane minimum and the barycentrics (most packets tested).
                return PacketClosest {
                    hit: false,
                    t: f32::INFINITY,
                    prim: 0,
                    b1: 0.0,
                    b2: 0.0,
                };
            }
            let cand = _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), t, ok);
            let m = _mm256_min_ps(cand, _mm256_permute2f128_ps::<1>(cand, cand));
            let m = _mm256_min_ps(m, _mm256_permute_ps::<0b01_00_11_10>(m));
            let m = _mm256_min_ps(m, _mm256_permute_ps::<0b10_11_00_01>(m));
            let eq = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(cand, m)) as u32 & mask;
            // `eq` is non-zero (the minimum is one of the hit lanes); the mask keeps the index
            // check away.
            let lane = (eq.trailing_zeros() as usize) & (LANES - 1);
            let (b1, b2) = (
                store(_mm256_mul_ps(v, inv_det)),
                store(_mm256_mul_ps(w, inv_det)),
            );
            PacketClosest {
                hit: true,
                t: _mm256_cvtss_f32(m),
                prim: p.prim[lane],
                b1: b1[lane],
                b2: b2[lane],
            }
        }
    }
}
