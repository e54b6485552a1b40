//! What a lost packet damaged in an H.264 picture, row by row.
//!
//! The depacketiser hands over whole NAL units only (a slice that lost a
//! fragment is dropped whole) and says where among them packets were lost
//! ([`AccessUnit::gaps`](crate::video::h264::AccessUnit)). Each slice's
//! header names its first macroblock (`first_mb_in_slice`); a slice runs up
//! to the next slice's first macroblock. So a slice whose successor arrived
//! with no loss between them covers its range intact, and every other range
//! (before the first slice that arrived, and from a slice followed by a loss
//! up to the next slice that arrived) is damaged: the decoder conceals it.
//! The extent of a slice followed by a loss cannot be known without decoding
//! it, so its whole range counts as damaged (conservative).
//!
//! Damage travels down the reference chain: a predicted picture copies
//! blocks from its references wherever its motion vectors point. Without
//! decoding the motion vectors (CAVLC/CABAC parsing of every macroblock) the
//! tracker bounds them: the damaged rows of every picture in the reference
//! window (the SPS's `max_num_ref_frames` newest reference pictures) are
//! widened by [`DamageParams::mv_px`] (the vertical motion bound) plus the
//! 6-tap interpolation filter's reach (3 rows), and the picture's own
//! damage by the deblocking filter's reach (3 rows above, 6 below: the
//! filter runs down the picture, and the next 4x4 block edge below passes
//! part of the first edge's change on). A motion vector may
//! point beyond the picture, where the reference's edge row repeats: damage
//! that touches the top or bottom row stays at that edge however the
//! content moves (with the measured motion it would otherwise leave the
//! rows it uncovers there unmasked). An IDR picture, or a
//! picture whose slices are all intra, starts clean; a reference picture
//! that went missing altogether (a jump in `frame_num`) damages every row
//! of the pictures that follow, up to the next IDR picture or the end of an
//! SEI recovery point's window. A recovery point (periodic intra refresh
//! sends one as each refresh cycle starts) says the pictures from its count
//! on are correct whatever the references before it held, so at the end of
//! its window only the damage of losses inside the window is left: that is
//! followed on a chain of its own from the SEI picture on, and replaces the
//! whole chain's when the count has passed. The next recovery point that
//! meets damage opens the next window.
//!
//! Streams with one slice per picture (x264's default) lose the whole
//! picture to any lost packet; streams sent for lossy links cap their slices
//! at one packet (`slice-max-size`), so a lost packet costs its rows.

/// Tunables of the damage tracking.
#[derive(Debug, Clone, PartialEq)]
pub struct DamageParams {
    /// Bound on the vertical motion between a picture and its references,
    /// pixels: damage in a reference spreads this far (plus the 3-row reach
    /// of the interpolation filter) into the pictures predicted from it.
    pub mv_px: u32,
    /// Rows the deblocking filter changes beside a damaged macroblock edge.
    pub deblock_px: u32,
    /// Follow the content's measured motion ([`DamageTracker::set_motion`])
    /// instead of the motion bound when a measurement is at hand (off by
    /// default: it masks less and lets SLAM track more frames, but a few
    /// rows it leaves unmasked differ from the lossless decode, by a grey
    /// level or more).
    pub follow_motion: bool,
    /// With a measured motion, damage in a reference reaches this much
    /// beyond the measured range (plus the measurement's resolution and
    /// the interpolation filter's reach), pixels: motion vectors that stray
    /// from the content's motion, and the change of motion from one
    /// picture to the next.
    pub motion_margin_px: u32,
}

impl Default for DamageParams {
    fn default() -> Self {
        Self {
            mv_px: 16,
            deblock_px: 3,
            follow_motion: false,
            motion_margin_px: 3,
        }
    }
}

use crate::video::motion::VerticalMotion;

/// The 6-tap luma interpolation filter reads this many rows beyond the
/// motion vector's integer position.
const INTERP_PX: u32 = 3;

/// The deblocking filter runs down the picture, edge after edge: below
/// damage, the macroblock edge's filter changes the rows it reaches (q0-q2),
/// and the next 4x4 block edge, 4 rows down and filtered after it, reads
/// them as its p-side and passes part of the change on (its p1-q1). So
/// damage reaches this many rows further below than above (seen: 1-2 rows
/// beyond the 3 of the first edge in 7 of 33 lossy streams, always below).
/// None when the filter's reach ([`DamageParams::deblock_px`]) is 0.
const DEBLOCK_CASCADE_PX: u32 = 3;

/// Reads bits of an RBSP (emulation prevention bytes already removed).
struct Bits<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Bits<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self { data, pos: 0 }
    }

    fn bit(&mut self) -> Option<u32> {
        let byte = *self.data.get(self.pos / 8)?;
        let b = (byte >> (7 - (self.pos % 8))) & 1;
        self.pos += 1;
        Some(u32::from(b))
    }

    fn bits(&mut self, n: u32) -> Option<u32> {
        let mut v = 0u32;
        for _ in 0..n {
            v = (v << 1) | self.bit()?;
        }
        Some(v)
    }

    /// Unsigned Exp-Golomb.
    fn ue(&mut self) -> Option<u32> {
        let mut zeros = 0;
        while self.bit()? == 0 {
            zeros += 1;
            if zeros > 31 {
                return None;
            }
        }
        let rest = self.bits(zeros)?;
        Some(((1u64 << zeros) - 1 + u64::from(rest)).min(u64::from(u32::MAX)) as u32)
    }

    /// Signed Exp-Golomb.
    fn se(&mut self) -> Option<i64> {
        let k = i64::from(self.ue()?);
        Some(if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) })
    }
}

/// A NAL unit's payload without its header byte and without emulation
/// prevention bytes.
pub(crate) fn rbsp(nal: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(nal.len());
    let mut zeros = 0;
    for &b in nal.iter().skip(1) {
        if zeros >= 2 && b == 3 {
            zeros = 0;
            continue;
        }
        zeros = if b == 0 { zeros + 1 } else { 0 };
        out.push(b);
    }
    out
}

/// What the damage tracking needs of a sequence parameter set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpsInfo {
    /// `seq_parameter_set_id`.
    pub id: u32,
    /// Picture width in macroblocks.
    pub width_mbs: u32,
    /// Frame height in macroblocks.
    pub height_mbs: u32,
    /// Only frame (progressive) macroblocks.
    pub frame_mbs_only: bool,
    /// `log2_max_frame_num`.
    pub log2_max_frame_num: u32,
    /// `max_num_ref_frames`.
    pub max_num_ref_frames: u32,
    /// `gaps_in_frame_num_value_allowed_flag`.
    pub frame_num_gaps_allowed: bool,
    /// Luma rows cropped at the top of the decoded picture.
    pub crop_top_px: u32,
    /// Separate colour planes (a colour plane id in each slice header).
    pub separate_colour_plane: bool,
}

fn skip_scaling_list(b: &mut Bits<'_>, size: usize) -> Option<()> {
    let (mut last, mut next) = (8i64, 8i64);
    for _ in 0..size {
        if next != 0 {
            let delta = b.se()?;
            next = (last + delta + 256).rem_euclid(256);
        }
        last = if next == 0 { last } else { next };
    }
    Some(())
}

/// Parse a sequence parameter set NAL unit (with its header byte).
pub fn parse_sps(nal: &[u8]) -> Option<SpsInfo> {
    let data = rbsp(nal);
    let mut b = Bits::new(&data);
    let profile = b.bits(8)?;
    b.bits(16)?; // constraint flags, level
    let id = b.ue()?;
    let mut separate_colour_plane = false;
    if matches!(
        profile,
        100 | 110 | 122 | 244 | 44 | 83 | 86 | 118 | 128 | 138 | 139 | 134 | 135
    ) {
        let chroma = b.ue()?;
        if chroma == 3 {
            separate_colour_plane = b.bit()? == 1;
        }
        b.ue()?; // bit depth luma
        b.ue()?; // bit depth chroma
        b.bit()?; // qpprime_y_zero_transform_bypass
        if b.bit()? == 1 {
            let lists = if chroma == 3 { 12 } else { 8 };
            for i in 0..lists {
                if b.bit()? == 1 {
                    skip_scaling_list(&mut b, if i < 6 { 16 } else { 64 })?;
                }
            }
        }
    }
    let log2_max_frame_num = b.ue()?.checked_add(4)?;
    if log2_max_frame_num > 16 {
        return None;
    }
    match b.ue()? {
        0 => {
            b.ue()?;
        }
        1 => {
            b.bit()?;
            b.se()?;
            b.se()?;
            let n = b.ue()?;
            if n > 255 {
                return None;
            }
            for _ in 0..n {
                b.se()?;
            }
        }
        _ => {}
    }
    let max_num_ref_frames = b.ue()?;
    let frame_num_gaps_allowed = b.bit()? == 1;
    let width_mbs = b.ue()?.checked_add(1)?;
    let map_units = b.ue()?.checked_add(1)?;
    let frame_mbs_only = b.bit()? == 1;
    if !frame_mbs_only {
        b.bit()?; // mb_adaptive_frame_field
    }
    b.bit()?; // direct_8x8_inference
    let mut crop_top_px = 0;
    if b.bit()? == 1 {
        b.ue()?;
        b.ue()?;
        let top = b.ue()?;
        // 4:2:0 (and 4:2:2): crop units are two luma rows per frame row.
        crop_top_px = top.saturating_mul(2 * if frame_mbs_only { 1 } else { 2 });
    }
    let height_mbs = map_units.checked_mul(if frame_mbs_only { 1 } else { 2 })?;
    if width_mbs > 1024 || height_mbs > 1024 {
        return None;
    }
    Some(SpsInfo {
        id,
        width_mbs,
        height_mbs,
        frame_mbs_only,
        log2_max_frame_num,
        max_num_ref_frames,
        frame_num_gaps_allowed,
        crop_top_px,
        separate_colour_plane,
    })
}

/// What the damage tracking needs of a picture parameter set: its id, its
/// SPS and whether it uses slice groups (FMO: macroblocks out of raster
/// order, so a lost slice's rows cannot be told).
pub fn parse_pps(nal: &[u8]) -> Option<(u32, u32, bool)> {
    let data = rbsp(nal);
    let mut b = Bits::new(&data);
    let id = b.ue()?;
    let sps = b.ue()?;
    b.bit()?; // entropy_coding_mode
    b.bit()?; // bottom_field_pic_order_in_frame_present
    let groups = b.ue()?;
    Some((id, sps, groups > 0))
}

/// The start of a slice header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SliceHeader {
    /// `first_mb_in_slice`.
    pub first_mb: u32,
    /// `slice_type` modulo 5: 0 P, 1 B, 2 I, 3 SP, 4 SI.
    pub slice_type: u32,
    /// `pic_parameter_set_id`.
    pub pps_id: u32,
    /// `frame_num` when the SPS was known.
    pub frame_num: Option<u32>,
}

impl SliceHeader {
    /// Intra only (I or SI): predicts from no other picture.
    pub fn is_intra(&self) -> bool {
        matches!(self.slice_type, 2 | 4)
    }
}

/// Parse a slice NAL unit's header up to `frame_num` (`sps_of` finds the
/// SPS of a PPS id).
pub fn parse_slice_header(
    nal: &[u8],
    sps_of: impl Fn(u32) -> Option<SpsInfo>,
) -> Option<SliceHeader> {
    // The header's first fields fit in a few bytes: no need to unescape all.
    let head = &nal[..nal.len().min(64)];
    let data = rbsp(head);
    let mut b = Bits::new(&data);
    let first_mb = b.ue()?;
    let slice_type = b.ue()? % 5;
    let pps_id = b.ue()?;
    let frame_num = sps_of(pps_id).and_then(|sps| {
        if sps.separate_colour_plane {
            b.bits(2)?;
        }
        b.bits(sps.log2_max_frame_num)
    });
    Some(SliceHeader {
        first_mb,
        slice_type,
        pps_id,
        frame_num,
    })
}

/// Damaged rows of a picture: `true` for a row whose pixels may differ from
/// what the encoder meant.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RowDamage {
    rows: Vec<bool>,
}

impl RowDamage {
    /// `height` intact rows.
    pub fn clean(height: usize) -> Self {
        Self {
            rows: vec![false; height],
        }
    }

    /// `height` damaged rows.
    pub fn full(height: usize) -> Self {
        Self {
            rows: vec![true; height],
        }
    }

    /// The rows, `true` where damaged.
    pub fn rows(&self) -> &[bool] {
        &self.rows
    }

    /// Damaged rows.
    pub fn count(&self) -> usize {
        self.rows.iter().filter(|d| **d).count()
    }

    /// Whether any row is damaged.
    pub fn any(&self) -> bool {
        self.rows.iter().any(|d| *d)
    }

    fn mark(&mut self, from: usize, to: usize) {
        let to = to.min(self.rows.len());
        if from < to {
            self.rows[from..to].fill(true);
        }
    }

    fn or(&mut self, other: &RowDamage) {
        for (a, b) in self.rows.iter_mut().zip(&other.rows) {
            *a |= *b;
        }
    }

    /// Every row a damaged row reaches when moved down by `lo` to `hi`
    /// rows (negative: up). A damaged run that touches the picture's top or
    /// bottom row keeps reaching that edge: a motion vector may point beyond
    /// the picture, where the reference's edge row is repeated, so the rows
    /// that content moving away from an edge uncovers are predicted from a
    /// damaged row.
    pub fn moved(&self, lo: i64, hi: i64) -> RowDamage {
        let n = self.rows.len() as i64;
        let mut out = RowDamage::clean(self.rows.len());
        let mut i = 0;
        while i < n {
            if self.rows[i as usize] {
                let start = i;
                while i < n && self.rows[i as usize] {
                    i += 1;
                }
                let a = if start == 0 {
                    0
                } else {
                    (start + lo).clamp(0, n)
                };
                let b = if i == n { n } else { (i + hi).clamp(0, n) };
                out.mark(a as usize, b as usize);
            } else {
                i += 1;
            }
        }
        out
    }

    /// Every row within `r` rows of a damaged one.
    pub fn dilated(&self, r: usize) -> RowDamage {
        let r = r as i64;
        self.moved(-r, r)
    }
}

/// One picture's verdict.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PictureDamage {
    /// Damaged luma rows of the coded picture (before cropping).
    pub coded: RowDamage,
    /// Luma rows cropped at the top (the decoded picture starts here).
    pub crop_top_px: u32,
    /// Damage of the picture's own slices (lost or unplaceable), before the
    /// reference chain was added, macroblock rows.
    pub own_mb_rows: usize,
}

impl PictureDamage {
    /// Damaged rows of the decoded (cropped) picture of `height` rows,
    /// decimated by `downscale` (a decimated row is damaged when any of its
    /// source rows is).
    pub fn rows_of(&self, height: u32, downscale: u32) -> RowDamage {
        let f = downscale.max(1) as usize;
        let h = height as usize;
        let top = self.crop_top_px as usize;
        let coded = self.coded.rows();
        let mut out = RowDamage::clean(h);
        for (y, r) in out.rows.iter_mut().enumerate() {
            *r = (0..f).any(|k| coded.get(top + y * f + k).copied().unwrap_or(true));
        }
        out
    }
}

/// Follows damage through a stream's pictures (see the module text).
#[derive(Debug)]
pub struct DamageTracker {
    params: DamageParams,
    sps: Vec<SpsInfo>,
    /// (pps id, sps id, slice groups).
    pps: Vec<(u32, u32, bool)>,
    /// Damage of the reference pictures in the window, newest first.
    refs: std::collections::VecDeque<RowDamage>,
    /// `frame_num` of the last reference picture.
    prev_ref_frame_num: Option<u32>,
    /// The recovery window opened by the last SEI recovery point that met
    /// damage, until its count has passed.
    recovery: Option<Recovery>,
    /// The content's vertical motion expected for the next picture, coded
    /// rows ([`DamageTracker::set_motion`]).
    motion: Option<VerticalMotion>,
}

/// An open recovery window: from the picture carrying an SEI recovery point
/// to the picture its `recovery_frame_cnt` names. Pictures from the target on
/// are correct whatever the references before the SEI held, so only the
/// damage of losses inside the window (its own reference chain, `fresh`)
/// outlives it.
#[derive(Debug)]
struct Recovery {
    /// `frame_num` of the picture carrying the SEI.
    start: u32,
    /// Its `recovery_frame_cnt`.
    count: u32,
    /// The reference window's damage counting only losses since `start`,
    /// newest first.
    fresh: std::collections::VecDeque<RowDamage>,
}

/// Whether packets were lost in an access unit, and where among its NAL
/// units.
#[derive(Debug, Clone, Copy)]
pub struct Losses<'a> {
    /// Packets lost (0: none).
    pub lost: u32,
    /// Positions among the NAL units where packets went missing (`k`: before
    /// NAL unit `k`; the unit count: at the end). Empty with `lost > 0`:
    /// the position is unknown and the whole picture counts as damaged.
    pub gaps: &'a [u32],
}

impl DamageTracker {
    /// A tracker knowing no parameter sets yet.
    pub fn new(params: DamageParams) -> Self {
        Self {
            params,
            sps: Vec::new(),
            pps: Vec::new(),
            refs: std::collections::VecDeque::new(),
            prev_ref_frame_num: None,
            recovery: None,
            motion: None,
        }
    }

    /// The content's vertical motion expected between the next picture and
    /// its references, in coded rows (measured on the pictures before it:
    /// [`crate::video::motion`]); `None`: unknown, the motion bound holds.
    pub fn set_motion(&mut self, motion: Option<VerticalMotion>) {
        self.motion = motion;
    }

    /// Whether a reference picture in the window carries damage (the next
    /// predicted picture may inherit it).
    pub fn has_damage(&self) -> bool {
        self.refs.iter().any(RowDamage::any)
    }

    /// The measured motion, when it is to be followed.
    fn followed(&self) -> Option<VerticalMotion> {
        self.motion.filter(|_| self.params.follow_motion)
    }

    /// Where a reference's damage can reach in the next picture: moved with
    /// the measured motion (the filters' reach is added to the picture's
    /// mask, not carried on), or spread by the motion bound and the
    /// interpolation filter's reach.
    fn reach(&self, d: &RowDamage) -> RowDamage {
        match self.followed() {
            Some(m) => {
                let pad = i64::from(self.params.motion_margin_px + m.step.saturating_sub(1));
                d.moved(i64::from(m.lo) - pad, i64::from(m.hi) + pad)
            }
            None => d.dilated((self.params.mv_px + INTERP_PX) as usize),
        }
    }

    /// Forget the reference chain (a new stream).
    pub fn reset(&mut self) {
        self.refs.clear();
        self.prev_ref_frame_num = None;
        self.recovery = None;
        self.motion = None;
    }

    /// The last picture could not be decoded at all: every reference in the
    /// window counts as damaged until the chain is reset.
    pub fn picture_lost(&mut self) {
        let fresh = self.recovery.iter_mut().flat_map(|w| w.fresh.iter_mut());
        for r in self.refs.iter_mut().chain(fresh) {
            *r = RowDamage::full(r.rows().len());
        }
        if self.refs.is_empty() {
            self.prev_ref_frame_num = None;
        }
    }

    /// One reference chain carried to the next picture: the references'
    /// damage as it reaches the picture (kept so: an older reference's moves
    /// add up picture by picture; a missing reference adds a fully damaged
    /// one), the picture's mask (its own damage `own`, what it inherits when
    /// it predicts, and the filters' reach), and what the chain keeps of it
    /// when it is a reference.
    ///
    /// The filters' reach beside the damage is carried down the chain with
    /// the bound, put only on this picture's mask with a measured motion: a
    /// row the 6-tap filter or the deblocking filter reaches takes a
    /// fraction of its neighbour's error (the outer taps weigh 1/32), so
    /// that fraction does not travel on as the damage's core does.
    fn carried(
        &self,
        refs: std::collections::VecDeque<RowDamage>,
        own: &RowDamage,
        missing_ref: bool,
        inter: bool,
        idr: bool,
    ) -> (std::collections::VecDeque<RowDamage>, RowDamage, RowDamage) {
        let h = own.rows().len();
        let mut refs: std::collections::VecDeque<RowDamage> = refs
            .into_iter()
            .map(|r| {
                if r.rows().len() == h {
                    self.reach(&r)
                } else {
                    RowDamage::full(h)
                }
            })
            .collect();
        if missing_ref {
            refs.push_front(RowDamage::full(h));
        }
        let mut core = own.clone();
        if inter {
            for r in &refs {
                core.or(r);
            }
        }
        let followed = !idr && self.followed().is_some();
        let deblock = i64::from(self.params.deblock_px);
        let cascade = if deblock > 0 {
            i64::from(DEBLOCK_CASCADE_PX)
        } else {
            0
        };
        let up = deblock + if followed { i64::from(INTERP_PX) } else { 0 };
        let coded = core.moved(-up, up + cascade);
        let kept = if followed && coded.any() {
            core
        } else {
            coded.clone()
        };
        (refs, coded, kept)
    }

    fn sps_of_pps(&self, pps_id: u32) -> Option<(SpsInfo, bool)> {
        let &(_, sps_id, fmo) = self.pps.iter().find(|p| p.0 == pps_id)?;
        let sps = *self.sps.iter().find(|s| s.id == sps_id)?;
        Some((sps, fmo))
    }

    /// Take an access unit's NAL units (without start codes) and its losses;
    /// returns the picture's damage, or `None` when it holds no slice the
    /// tracker can place (no picture, or parameter sets unknown).
    pub fn picture(&mut self, nals: &[&[u8]], losses: Losses<'_>) -> Option<PictureDamage> {
        let mut slices: Vec<(u32, SliceHeader, bool, u8)> = Vec::new();
        let mut recovery_cnt = None;
        for (k, nal) in nals.iter().enumerate() {
            let Some(&h) = nal.first() else { continue };
            match h & 0x1f {
                7 => {
                    if let Some(s) = parse_sps(nal) {
                        self.sps.retain(|x| x.id != s.id);
                        self.sps.push(s);
                    }
                }
                8 => {
                    if let Some(p) = parse_pps(nal) {
                        self.pps.retain(|x| x.0 != p.0);
                        self.pps.push(p);
                    }
                }
                6 => {
                    if let Some(n) = sei_recovery_frame_cnt(nal) {
                        recovery_cnt = Some(n);
                    }
                }
                t @ (1 | 5) => {
                    let sps_of = |pps: u32| self.sps_of_pps(pps).map(|x| x.0);
                    if let Some(sh) = parse_slice_header(nal, sps_of) {
                        slices.push((k as u32, sh, t == 5, (h >> 5) & 3));
                    }
                }
                _ => {}
            }
        }
        let first = slices.first()?;
        let (sps, fmo) = self.sps_of_pps(first.1.pps_id)?;
        let idr = slices.iter().any(|s| s.2);
        let is_ref = slices.iter().any(|s| s.3 != 0);
        let frame_num = first.1.frame_num;
        let total = sps.width_mbs * sps.height_mbs;
        let coded_h = (sps.height_mbs * 16) as usize;
        let loss = losses.lost > 0 || !losses.gaps.is_empty();

        // The picture's own damage, in macroblock rows.
        let mut own_mbs = RowDamage::clean(sps.height_mbs as usize);
        if loss {
            if (losses.gaps.is_empty() && losses.lost > 0) || fmo || !sps.frame_mbs_only {
                own_mbs = RowDamage::full(sps.height_mbs as usize);
            } else {
                let mut firsts: Vec<u32> = slices.iter().map(|s| s.1.first_mb).collect();
                firsts.sort_unstable();
                firsts.dedup();
                let mark = |d: &mut RowDamage, from: u32, to: u32| {
                    let (a, b) = (from / sps.width_mbs, to.min(total).div_ceil(sps.width_mbs));
                    d.mark(a as usize, b as usize);
                };
                if let Some(&lo) = firsts.first()
                    && lo > 0
                {
                    mark(&mut own_mbs, 0, lo);
                }
                for (i, s) in slices.iter().enumerate() {
                    let f = s.1.first_mb;
                    let next_f = firsts.iter().copied().find(|&x| x > f).unwrap_or(total);
                    let gap_between =
                        |lo: u32, hi: u32| losses.gaps.iter().any(|&g| g > lo && g <= hi);
                    let intact = if next_f >= total {
                        i + 1 == slices.len() && !losses.gaps.iter().any(|&g| g > s.0)
                    } else {
                        slices
                            .get(i + 1)
                            .is_some_and(|n| n.1.first_mb == next_f && !gap_between(s.0, n.0))
                    };
                    if !intact {
                        mark(&mut own_mbs, f, next_f);
                    }
                }
            }
        }
        let own_mb_rows = own_mbs.count();
        let mut coded = RowDamage::clean(coded_h);
        for (r, d) in own_mbs.rows().iter().enumerate() {
            if *d {
                coded.mark(r * 16, r * 16 + 16);
            }
        }

        // The reference chain.
        let max = 1u32 << sps.log2_max_frame_num;
        let missing_ref = !idr
            && match (self.prev_ref_frame_num, frame_num) {
                (Some(p), Some(f)) => f != (p + 1) % max && (loss || !sps.frame_num_gaps_allowed),
                (None, _) | (_, None) => true,
            };
        let inter = !idr && slices.iter().any(|s| !s.1.is_intra());
        if idr {
            self.refs.clear();
            self.recovery = None;
        }
        let own = coded;
        let refs = std::mem::take(&mut self.refs);
        let (refs, mut coded, mut kept) = self.carried(refs, &own, missing_ref, inter, idr);
        self.refs = refs;
        // An SEI recovery point: pictures from its count on are correct
        // whatever came before it, so at the end of its window only the
        // damage of losses inside the window is left (followed on a chain
        // of its own, which starts from the SEI picture's own losses).
        // The SEI picture opening a window starts its chain: its references
        // are the past's, so only its own losses count.
        let mut opened = false;
        if let (Some(count), Some(start), None) = (recovery_cnt, frame_num, &self.recovery)
            && coded.any()
        {
            let fresh = std::collections::VecDeque::new();
            self.recovery = Some(Recovery {
                start,
                count,
                fresh,
            });
            opened = true;
        }
        if let Some(mut w) = self.recovery.take() {
            let (fresh, fresh_coded, fresh_kept) =
                self.carried(w.fresh, &own, missing_ref && !opened, inter && !opened, idr);
            let passed = frame_num.is_some_and(|f| (f + max - w.start) % max >= w.count);
            if passed {
                (self.refs, coded, kept) = (fresh, fresh_coded, fresh_kept);
            } else {
                w.fresh = fresh;
                if is_ref {
                    push_ref(&mut w.fresh, fresh_kept, sps.max_num_ref_frames);
                }
                self.recovery = Some(w);
            }
        }
        if is_ref {
            push_ref(&mut self.refs, kept, sps.max_num_ref_frames);
            self.prev_ref_frame_num = frame_num;
        }
        Some(PictureDamage {
            coded,
            crop_top_px: sps.crop_top_px,
            own_mb_rows,
        })
    }
}

/// Put a reference picture's damage at the front of a chain of at most
/// `max_refs` (the SPS's `max_num_ref_frames`, at least 1).
fn push_ref(refs: &mut std::collections::VecDeque<RowDamage>, d: RowDamage, max_refs: u32) {
    refs.push_front(d);
    refs.truncate(max_refs.max(1) as usize);
}

/// The `recovery_frame_cnt` of an SEI NAL unit's recovery point message.
fn sei_recovery_frame_cnt(nal: &[u8]) -> Option<u32> {
    let data = rbsp(nal);
    let mut i = 0;
    while i < data.len() && data[i] != 0x80 {
        let mut ty = 0u32;
        while *data.get(i)? == 0xff {
            ty += 255;
            i += 1;
        }
        ty += u32::from(*data.get(i)?);
        i += 1;
        let mut size = 0usize;
        while *data.get(i)? == 0xff {
            size += 255;
            i += 1;
        }
        size += usize::from(*data.get(i)?);
        i += 1;
        if ty == 6 {
            let end = (i + size).min(data.len());
            return Bits::new(&data[i..end]).ue();
        }
        i = i.saturating_add(size);
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Write Exp-Golomb fields into bytes.
    struct W {
        bits: Vec<u8>,
    }

    impl W {
        fn new() -> Self {
            Self { bits: Vec::new() }
        }
        fn u(&mut self, n: u32, v: u32) -> &mut Self {
            for k in (0..n).rev() {
                self.bits.push(((v >> k) & 1) as u8);
            }
            self
        }
        fn ue(&mut self, v: u32) -> &mut Self {
            let x = v + 1;
            let n = 32 - x.leading_zeros();
            self.u(n - 1, 0).u(n, x)
        }
        fn nal(&mut self, header: u8) -> Vec<u8> {
            self.bits.push(1);
            while !self.bits.len().is_multiple_of(8) {
                self.bits.push(0);
            }
            let mut out = vec![header];
            for c in self.bits.chunks(8) {
                out.push(c.iter().fold(0u8, |a, b| (a << 1) | b));
            }
            out
        }
    }

    /// Baseline SPS: `w`x`h` macroblocks, frame_num in 4 bits, 1 reference.
    fn sps(w: u32, h: u32) -> Vec<u8> {
        W::new()
            .u(8, 66)
            .u(16, 30)
            .ue(0)
            .ue(0) // log2_max_frame_num - 4
            .ue(2) // poc type 2
            .ue(1) // max_num_ref_frames
            .u(1, 0)
            .ue(w - 1)
            .ue(h - 1)
            .u(1, 1)
            .u(1, 1)
            .u(1, 0)
            .u(1, 0)
            .nal(0x67)
    }

    fn pps() -> Vec<u8> {
        W::new().ue(0).ue(0).u(1, 0).u(1, 0).ue(0).nal(0x68)
    }

    fn slice(idr: bool, first_mb: u32, slice_type: u32, frame_num: u32) -> Vec<u8> {
        W::new()
            .ue(first_mb)
            .ue(slice_type)
            .ue(0)
            .u(4, frame_num)
            .nal(if idr { 0x65 } else { 0x41 })
    }

    fn run(t: &mut DamageTracker, nals: &[Vec<u8>], lost: u32, gaps: &[u32]) -> PictureDamage {
        let refs: Vec<&[u8]> = nals.iter().map(Vec::as_slice).collect();
        t.picture(&refs, Losses { lost, gaps }).unwrap()
    }

    /// An IDR picture of 40x30 macroblocks in 4 slices starting at
    /// macroblock rows 0, 8, 16 and 24, with its parameter sets.
    fn idr_in_four_slices() -> Vec<Vec<u8>> {
        vec![
            sps(40, 30),
            pps(),
            slice(true, 0, 7, 0),
            slice(true, 320, 7, 0),
            slice(true, 640, 7, 0),
            slice(true, 960, 7, 0),
        ]
    }

    /// Macroblock rows (of 16 pixel rows) with any damaged pixel row.
    fn mb_rows(d: &PictureDamage) -> Vec<usize> {
        (0..d.coded.rows().len() / 16)
            .filter(|r| d.coded.rows()[r * 16..r * 16 + 16].iter().any(|x| *x))
            .collect()
    }

    #[test]
    fn parameter_sets_and_slice_headers_parse() {
        let s = parse_sps(&sps(40, 30)).unwrap();
        assert_eq!(
            (s.width_mbs, s.height_mbs, s.log2_max_frame_num),
            (40, 30, 4)
        );
        assert_eq!(parse_pps(&pps()), Some((0, 0, false)));
        let h = parse_slice_header(&slice(false, 123, 5, 7), |_| Some(s)).unwrap();
        assert_eq!((h.first_mb, h.slice_type, h.frame_num), (123, 0, Some(7)));
        assert!(parse_sps(&[0x67, 66]).is_none(), "truncated SPS");
    }

    #[test]
    fn a_lost_slice_damages_its_rows_and_its_successors_by_the_motion_bound() {
        let params = DamageParams {
            mv_px: 16,
            deblock_px: 3,
            ..Default::default()
        };
        let mut t = DamageTracker::new(params);
        let idr = idr_in_four_slices();
        assert!(!run(&mut t, &idr, 0, &[]).coded.any());
        // P picture: the slice starting at row 8 was lost (gap before NAL 1).
        let p1 = vec![
            slice(false, 0, 5, 1),
            slice(false, 640, 5, 1),
            slice(false, 960, 5, 1),
        ];
        let d = run(&mut t, &p1, 1, &[1]);
        // Slice 0's extent is unknown (it is followed by the loss): rows 0-15
        // damaged, plus the deblocking reach (3 + 3 rows below) into row 16.
        assert_eq!(mb_rows(&d), (0..17).collect::<Vec<_>>());
        assert_eq!(d.own_mb_rows, 16);
        // The next P picture arrives whole: the damage spreads by 16 + 3 + 6
        // rows (motion, interpolation, deblocking): from row 262 to 287.
        let p2 = vec![slice(false, 0, 5, 2), slice(false, 960, 5, 2)];
        let d = run(&mut t, &p2, 0, &[]);
        assert_eq!(d.own_mb_rows, 0);
        assert_eq!(mb_rows(&d), (0..18).collect::<Vec<_>>());
        assert_eq!(d.coded.count(), 287);
        // An intra-only picture starts clean; so does an IDR.
        let i3 = vec![slice(false, 0, 7, 3)];
        assert!(!run(&mut t, &i3, 0, &[]).coded.any());
    }

    #[test]
    fn damage_moves_with_the_measured_motion() {
        let mut t = DamageTracker::new(DamageParams {
            motion_margin_px: 4,
            follow_motion: true,
            ..Default::default()
        });
        let idr = vec![
            sps(40, 30),
            pps(),
            slice(true, 0, 7, 0),
            slice(true, 320, 7, 0),
        ];
        assert!(!run(&mut t, &idr, 0, &[]).coded.any());
        // Rows 0-255 lost (the first slice is followed by the loss), plus
        // the deblocking reach below (3 + 3 rows): 0-261.
        let p1 = vec![slice(false, 0, 5, 1), slice(false, 640, 5, 1)];
        assert_eq!(run(&mut t, &p1, 1, &[1]).coded.count(), 262);
        // The content moves down 8-12 rows, measured to 4 rows: the damage
        // goes with it, 4 + 3 rows beyond (margin, resolution) at each end,
        // and stays at the top edge (the rows the content uncovers there
        // are predicted from the reference's damaged top row): rows 0-280;
        // the filters' reach (3 + 3 rows, and 3 more below) is added to the
        // picture's mask, 0-289, not carried on.
        let down = VerticalMotion {
            lo: 8,
            hi: 12,
            step: 4,
            blocks: 30,
        };
        t.set_motion(Some(down));
        let d = run(&mut t, &[slice(false, 0, 5, 2)], 0, &[]);
        assert_eq!(d.coded.count(), 290);
        // Moving up 36-40 rows, the top rows leave the picture: rows 0-280
        // go to 0-251, the mask to 0-260.
        t.set_motion(Some(VerticalMotion {
            lo: -40,
            hi: -36,
            ..down
        }));
        let d = run(&mut t, &[slice(false, 0, 5, 3)], 0, &[]);
        assert_eq!(d.coded.count(), 261);
        // Unknown motion: the bound (16 + 3 rows, then 3 + 3 of deblocking).
        t.set_motion(None);
        let d = run(&mut t, &[slice(false, 0, 5, 4)], 0, &[]);
        assert_eq!(d.coded.count(), 252 + 19 + 6);
        assert!(t.has_damage());
        run(&mut t, &idr, 0, &[]);
        assert!(!t.has_damage(), "an IDR picture ends it");
    }

    #[test]
    fn damage_at_an_edge_stays_at_it_when_the_content_moves_away() {
        let params = DamageParams {
            motion_margin_px: 0,
            follow_motion: true,
            ..Default::default()
        };
        let idr = idr_in_four_slices();
        let motion = |lo, hi| VerticalMotion {
            lo,
            hi,
            step: 1,
            blocks: 30,
        };
        // The last slice lost: the one before it, followed by the loss, is
        // damaged too (rows 256-479, 253-479 with the deblocking). Then the
        // content moves up 8-12 rows: the rows it uncovers at the bottom
        // are predicted from the reference's bottom row, repeated beyond
        // the edge. The reference's damage (the deblocking's reach kept, as
        // no motion was measured for it) runs 241-479 in the next picture,
        // the mask 235-479 with the filters' reach (without the edge:
        // 235-477).
        let mut t = DamageTracker::new(params.clone());
        run(&mut t, &idr, 0, &[]);
        let p1 = vec![
            slice(false, 0, 5, 1),
            slice(false, 320, 5, 1),
            slice(false, 640, 5, 1),
        ];
        assert_eq!(run(&mut t, &p1, 1, &[3]).coded.count(), 480 - 253);
        t.set_motion(Some(motion(-12, -8)));
        let d = run(&mut t, &[slice(false, 0, 5, 2)], 0, &[]);
        assert_eq!(d.coded.count(), 480 - 235);
        assert!(d.coded.rows()[479] && !d.coded.rows()[234]);
        // The first slice lost (rows 0-127, 0-133 with the deblocking's
        // reach below), then the content moves down 20-24 rows: the damage
        // stays at the top (0-157), the mask 0-166 (without the edge:
        // 14-166).
        let mut t = DamageTracker::new(params);
        run(&mut t, &idr, 0, &[]);
        let p1 = vec![
            slice(false, 320, 5, 1),
            slice(false, 640, 5, 1),
            slice(false, 960, 5, 1),
        ];
        assert_eq!(run(&mut t, &p1, 1, &[0]).coded.count(), 128 + 6);
        t.set_motion(Some(motion(20, 24)));
        let d = run(&mut t, &[slice(false, 0, 5, 2)], 0, &[]);
        assert_eq!(d.coded.count(), 167);
        assert!(d.coded.rows()[0] && d.coded.rows()[166] && !d.coded.rows()[167]);
    }

    #[test]
    fn a_missing_reference_picture_damages_everything_until_the_idr() {
        let mut t = DamageTracker::new(DamageParams::default());
        let idr = vec![sps(20, 15), pps(), slice(true, 0, 7, 0)];
        assert!(!run(&mut t, &idr, 0, &[]).coded.any());
        // frame_num 1 never came: picture 2's reference is missing.
        let d = run(&mut t, &[slice(false, 0, 5, 2)], 3, &[0]);
        assert_eq!(d.coded.count(), d.coded.rows().len());
        let d = run(&mut t, &[slice(false, 0, 5, 3)], 0, &[]);
        assert_eq!(d.coded.count(), d.coded.rows().len(), "carried on");
        let idr = vec![slice(true, 0, 7, 0)];
        assert!(!run(&mut t, &idr, 0, &[]).coded.any());
        // A loss whose position is unknown (RTSP) damages the whole picture.
        let d = run(&mut t, &[slice(false, 0, 5, 1)], 1, &[]);
        assert_eq!(d.coded.count(), d.coded.rows().len());
    }

    /// An SEI NAL unit holding one recovery point message.
    fn sei_recovery(count: u32) -> Vec<u8> {
        let mut payload = W::new();
        payload.ue(count).u(1, 1).u(1, 0).u(2, 0);
        while !payload.bits.len().is_multiple_of(8) {
            payload.bits.push(0);
        }
        let size = (payload.bits.len() / 8) as u32;
        let mut w = W::new();
        w.u(8, 6).u(8, size);
        w.bits.extend_from_slice(&payload.bits);
        w.nal(0x06)
    }

    #[test]
    fn intra_refresh_clears_at_each_recovery_point_and_keeps_only_the_windows_own_losses() {
        // x264's periodic intra refresh: one IDR picture, then P pictures
        // with a recovery point SEI every 6 pictures (count 5); 20x30
        // macroblocks in two slices (macroblock rows 0-14 and 15-29).
        let mut t = DamageTracker::new(DamageParams::default());
        // Picture `n`'s NAL units without the slice `lost` (0: top, 1:
        // bottom), and where the loss was among them.
        let picture = |n: u32, lost: Option<usize>| {
            let fnum = n % 16;
            let mut nals = Vec::new();
            if n.is_multiple_of(6) {
                nals.push(sei_recovery(5));
            }
            let mut gaps = Vec::new();
            for (k, first_mb) in [0, 300].into_iter().enumerate() {
                if lost == Some(k) {
                    gaps.push(nals.len() as u32);
                } else {
                    nals.push(slice(false, first_mb, 5, fnum));
                }
            }
            (nals, gaps)
        };
        let idr = vec![
            sps(20, 30),
            pps(),
            slice(true, 0, 7, 0),
            slice(true, 300, 7, 0),
        ];
        assert!(!run(&mut t, &idr, 0, &[]).coded.any());
        let mut damaged = Vec::new();
        // Pictures 1-40; the top slice is lost at 2 (before a window), 10
        // (inside the window opened at 6), 20 (before the window opened at
        // 24) and 26 (inside it).
        for n in 1..=40u32 {
            let lost = [2, 10, 20, 26].contains(&n).then_some(0);
            let (nals, gaps) = picture(n, lost);
            let d = run(&mut t, &nals, gaps.len() as u32, &gaps);
            damaged.push((n, mb_rows(&d)));
        }
        let rows = |n: u32| damaged[(n - 1) as usize].1.clone();
        assert!(rows(1).is_empty());
        assert_eq!(
            rows(2),
            (0..16).collect::<Vec<_>>(),
            "top slice and deblocking"
        );
        assert!(
            rows(10).len() > 24,
            "the first loss has spread: {:?}",
            rows(10)
        );
        // Window 6..11: the loss before it is gone at 11; the loss at 10 is
        // left, as it was one picture after the first loss.
        assert_eq!(rows(11), rows(3));
        assert_eq!(rows(11), (0..17).collect::<Vec<_>>());
        // The window at 12..17 had no loss: clean from 17 to the loss at 20.
        assert!(!rows(16).is_empty());
        for n in 17..20 {
            assert!(rows(n).is_empty(), "picture {n}: {:?}", rows(n));
        }
        // Window 24..29 with a loss at 26 (and one at 20 before it): at 29
        // only the loss at 26 is left, spread by three pictures' bound.
        assert!(rows(28).len() > rows(29).len());
        assert_eq!(rows(29), rows(5), "as three pictures after the first loss");
        // The window 30..35 opens on the damage 29 left, and clears it.
        assert!(!rows(34).is_empty());
        for n in 35..=40 {
            assert!(rows(n).is_empty(), "picture {n}: {:?}", rows(n));
        }
    }

    #[test]
    fn a_lost_tail_damages_from_the_last_slice_to_the_end() {
        let mut t = DamageTracker::new(DamageParams {
            mv_px: 0,
            deblock_px: 0,
            ..Default::default()
        });
        let idr = vec![
            sps(10, 10),
            pps(),
            slice(true, 0, 7, 0),
            slice(true, 50, 7, 0),
        ];
        // The loss after the second slice: rows 5-9 in doubt.
        let d = run(&mut t, &idr, 1, &[4]);
        assert_eq!(mb_rows(&d), (5..10).collect::<Vec<_>>());
        // First slice missing: rows before the first slice that arrived.
        let d = run(
            &mut t,
            &[sps(10, 10), pps(), slice(true, 30, 7, 0)],
            1,
            &[2],
        );
        assert_eq!(mb_rows(&d), (0..3).collect::<Vec<_>>());
    }

    #[test]
    fn cropped_and_decimated_rows_map_onto_the_coded_rows() {
        let mut coded = RowDamage::clean(32);
        coded.mark(16, 32);
        let d = PictureDamage {
            coded,
            crop_top_px: 2,
            own_mb_rows: 1,
        };
        let r = d.rows_of(28, 1);
        assert_eq!(r.rows().iter().position(|x| *x), Some(14));
        let r = d.rows_of(14, 2);
        assert_eq!(r.rows().iter().position(|x| *x), Some(7));
    }
}
