//! Options of [`super::fit`], one group per stage: input, fit renders, pre-estimation, joint
//! optimization, finish, and the run controls (threads, stop flag, progress, per-iteration
//! callback).

use super::anneal;
use super::joint::IterLog;
use crate::pattern::WeavePattern;
use crate::progress::{NoProgress, Progress};
use crate::scene::LightRig;
use anyhow::{bail, Context, Result};
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Joint (the paper's method) or separate (pattern first, then appearance) optimization.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FitMode {
    /// Annealing and gradient descent in the same loop.
    Joint,
    /// First half: annealing of the discrete parameters only; second half: gradient descent only.
    Separate,
}

impl std::str::FromStr for FitMode {
    type Err = anyhow::Error;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "joint" => Ok(FitMode::Joint),
            "separate" => Ok(FitMode::Separate),
            _ => bail!("unknown fit mode {s:?} (joint, separate)"),
        }
    }
}

/// Callback run after every iteration.
pub type IterCallback = Arc<dyn Fn(&IterLog) + Send + Sync>;

/// What the fit is given besides the image.
#[derive(Clone, Debug)]
pub struct InputOptions {
    /// Run `prep` (rectify, regularize, grid) on the input; otherwise the input is one repeat.
    pub prep: bool,
    /// Grid `(n_e, n_a)` of an input without prep; detected from the image when `None`.
    pub grid: Option<(usize, usize)>,
    /// Fixed pattern: no pattern estimation, no cell proposals (n_p, n_f are still annealed).
    pub pattern: Option<WeavePattern>,
}

impl Default for InputOptions {
    fn default() -> Self {
        InputOptions { prep: true, grid: None, pattern: None }
    }
}

/// The fit renders and the loss.
#[derive(Clone, Debug)]
pub struct RenderSettings {
    /// Pixels per pattern cell of the fit renders.
    pub px_per_cell: u32,
    /// Samples per pixel of the fit renders.
    pub spp: u32,
    /// Samples per pixel of the final render.
    pub final_spp: u32,
    /// Block size of the loss's box filter (pixels; 1 = per-pixel).
    pub loss_block: u32,
    /// Render and proposal seed.
    pub seed: u64,
    /// Light rig of the fit scene.
    pub lights: LightRig,
    /// Other rigs the light stage of a photo fit (`refine::fit_light_direction_from`) tries
    /// against `lights` once the pattern is settled, each kept only where it lowers the loss by
    /// the stage's margin: where `lights` was estimated from the photo
    /// (`capture::CaptureEstimate::apply`) rather than given, the default rig is one. Empty when
    /// the user named the rig.
    pub rival_lights: Vec<LightRig>,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            px_per_cell: 16,
            spp: 4,
            final_spp: 256,
            loss_block: 2,
            seed: 1,
            lights: LightRig::default_rig(),
            rival_lights: Vec::new(),
        }
    }
}

/// Pre-estimation: candidate patterns, their warm-up, the starts of the joint runs.
#[derive(Clone, Debug)]
pub struct PreOptions {
    /// Run the pre-estimation (pattern sweep, network, colours); otherwise start from twill + grey.
    pub enabled: bool,
    /// Pixels per cell of the pattern pre-estimation renders (0: the fit's; coarser renders
    /// cannot tell a pattern from its inverse with swapped colours).
    pub px_per_cell: u32,
    /// Pixels per cell of the warm-up's shape scans (radius and ply grids; 0, the default: those
    /// of the ranking), never more than the ranking's. Coarser scans are faster but not free: at
    /// 8 px per cell (half the fit's) the warm-up of a 5×5 own render took 16 instead of 36 CPU s
    /// with the same pattern, but the Mitsuba twill d03 came back with 1 ply at 27.6 dB instead of
    /// 29.8 dB (docs/benchmarks.md, session 18): the ply stripes and lobes need the pixels.
    pub scan_px_per_cell: u32,
    /// Pixels per cell of the shape scans' radius grids (the common radius and each family's;
    /// 0, the default: those of the scans, `scan_px_per_cell`), never more than the scans'. The
    /// ply-count pass stays at the scans' pixels (`preestimate::scan_shape` says why). Off by
    /// default: at 8 px the warm-up of the whole-path eval took 36 % less CPU with the same
    /// patterns and crop PSNR, but two of the four one-repeat targets lost 1 dB (41.3 instead of
    /// 42.3 on target 3: the coarse grid settled on another radius and the warm-up's loss was 4
    /// times the 16-px one's; docs/benchmarks.md, session 19).
    pub radius_scan_px_per_cell: u32,
    /// Samples per pixel of the pre-estimation renders.
    pub spp: u32,
    /// Best patterns of the coarse candidate ranking that get a warm-up (the best named weave and
    /// the labellings read from the picture always get one too).
    pub shortlist: usize,
    /// Levenberg–Marquardt iterations per round of each warm-up (see `refine::polish`).
    pub warmup: usize,
    /// Maximum greedy sweeps over the cells of each start.
    pub max_sweeps: usize,
    /// Most joint runs (each from a warmed-up candidate; the iterations are shared out).
    pub starts: usize,
    /// A runner-up gets its own run when its warm-up loss is within this fraction of the leader's.
    pub start_margin: f32,
    /// Read the target with the pre-estimator network (the model in `model`, else the shipped one
    /// built into the binary): its pattern joins the shortlist when the ranking did not pick it.
    pub network: bool,
    /// Pre-estimator model file replacing the shipped one.
    pub model: Option<PathBuf>,
    /// Read each cell's over/under from the prepared photo's structure (`cell_cues`): the reading
    /// joins the shortlist, and after the finish it replaces the fit's pattern where the loss
    /// cannot tell the two apart (prepared photos with free cells only).
    pub cell_cues: bool,
    /// Scan where the ply twist starts along each family (`YarnShape::ply_origin`) with the ply
    /// counts of the warm-up's shape scans: on for a prepared photo, whose crop starts wherever
    /// preparation put it; off for a one-repeat input, framed at the model's repeat edge.
    pub twist_origin: bool,
    /// A fixed pattern (`InputOptions::pattern`) is fitted in the cyclic shift of it that the
    /// crop's phase shows (`candidates::rank_shifts`): on for a prepared photo, whose crop
    /// starts at the yarn boundaries preparation found, not where the given repeat starts; off
    /// for a one-repeat input, taken as framed.
    pub shift_fixed_pattern: bool,
    /// On a prepared photo, find the key light's direction before the pattern search, on a probe
    /// of the pattern the picture reads (`light_first`), so that the warm-up, the view and the
    /// joint runs compare patterns under the photo's light instead of the rig's fixed one. Off
    /// with `FinishOptions::light_direction`.
    pub light_first: bool,
}

impl Default for PreOptions {
    fn default() -> Self {
        PreOptions {
            enabled: true,
            px_per_cell: 0,
            scan_px_per_cell: 0,
            radius_scan_px_per_cell: 0,
            spp: 2,
            shortlist: 1,
            warmup: 8,
            max_sweeps: 1,
            starts: 2,
            start_margin: 0.15,
            // On: the network reads the fit's view (per-cell logits); its pattern is one more
            // candidate, judged by the same warm-up loss as the ranked one (docs/design.md §4.3).
            network: true,
            model: None,
            cell_cues: true,
            twist_origin: false,
            shift_fixed_pattern: false,
            light_first: true,
        }
    }
}

/// Default iterations of the joint loop, shared out over its runs. 30 since session 22 (100
/// before): with the calibrated start temperature of [`anneal::ACCEPT0`] the runs spend them
/// near the best state, and the finish's rivals and Levenberg–Marquardt polish take the
/// appearance the rest of the way. 50 and 30 gave the same patterns and crop PSNR within the
/// scenes' noise on the own, Mitsuba and one-repeat checks (docs/benchmarks.md, session 22).
pub const JOINT_ITERATIONS: usize = 30;

/// The joint loop: annealing of the discrete parameters and Adam on the continuous ones.
#[derive(Clone, Debug)]
pub struct JointOptions {
    /// Joint or separate optimization.
    pub mode: FitMode,
    /// Iterations, shared out over the runs.
    pub iterations: usize,
    /// Adam step size as a fraction of each parameter's range.
    pub lr: f32,
    /// Radii step every this many iterations (0: radii fixed).
    pub radius_every: usize,
    /// Initial temperature.
    pub t0: f64,
    /// Temperature decay per iteration.
    pub decay: f64,
    /// Energy per unit MSE; calibrated when `None`.
    pub energy_scale: Option<f64>,
    /// Probability with which the calibration's median uphill proposal is accepted at `t0`
    /// ([`anneal::ACCEPT0`]).
    pub accept0: f64,
    /// End a run once its best loss has stopped falling (`joint::plateau_window` iterations
    /// without a 0.1 % fall); off (the default): every run takes its whole share of
    /// `iterations`. Off because the annealer finds its better discrete states late, while it
    /// cools: on, the fit is a quarter to a third faster and sometimes worse (docs/benchmarks.md,
    /// "Session 9: fit time").
    pub plateau_stop: bool,
}

impl Default for JointOptions {
    fn default() -> Self {
        JointOptions {
            mode: FitMode::Joint,
            iterations: JOINT_ITERATIONS,
            lr: 0.03,
            radius_every: 5,
            t0: anneal::T0,
            decay: anneal::DECAY,
            energy_scale: None,
            accept0: anneal::ACCEPT0,
            plateau_stop: false,
        }
    }
}

/// The finish of the best state.
#[derive(Clone, Debug)]
pub struct FinishOptions {
    /// Finish the joint runs: the best state against its rivals, then single-cell contests.
    pub enabled: bool,
    /// Levenberg–Marquardt iterations per round that finish the best state and its rivals.
    pub lm_iters: usize,
    /// Samples per pixel of the last polish of the winner (0: none). The 4-spp fit renders carry
    /// more noise than the misfit left after the finish; a fixed sample set at higher spp moves
    /// the optimum closer to the noise-free one.
    pub fine_spp: u32,
    /// Spatially varying body colour (paper §7.2): after the finish, optimise per-texel
    /// multipliers of R^B/S^B (this many texels per cell side; 0 = off).
    pub svcolor: u32,
    /// Yarn-dyed colours (`yarn_dyed`): on a prepared photo, after the finish, one body-colour
    /// multiplier per warp and weft yarn of the repeat, kept only where it lowers the loss by a
    /// fifth (stripes, checks). Not with `svcolor`, which is the finer texture.
    pub yarn_colours: bool,
    /// On a prepared photo, turn the light rig about the cloth normal and tilt its front light
    /// where that lowers the loss, before the winner's polish (`refine::fit_light_direction`):
    /// the photo's light comes from wherever it was put, the rig's from one fixed direction.
    pub light_direction: bool,
    /// On a prepared photo, after the light direction, try the yarns as smooth single plies
    /// without fibre relief under a light scanned for them, kept where that lowers the loss by a
    /// margin (`smooth_yarns`: the sharp crown highlight of a glossy tube).
    pub smooth_yarns: bool,
    /// On a prepared photo whose fit ends on a plain weave of a few yarns, try the yarns as
    /// working in pairs or threes that preparation read as one (the 2 × 2 and 3 × 3 baskets on a
    /// finer grid), kept where that lowers the loss by a clear margin (`paired`).
    pub grouped_yarns: bool,
    /// On a prepared photo, after the last descent, step a yarn family's body colours along their
    /// level (the exposure taking what would pass 1) where that lowers the loss by a margin and the
    /// held-out samples agree (`family_level`: a bright family held at its colours' bound).
    pub family_levels: bool,
}

impl Default for FinishOptions {
    fn default() -> Self {
        FinishOptions {
            enabled: true,
            lm_iters: 6,
            fine_spp: 16,
            svcolor: 0,
            yarn_colours: true,
            light_direction: true,
            smooth_yarns: true,
            grouped_yarns: true,
            family_levels: true,
        }
    }
}

/// How the fit runs: threads, cancellation, progress and per-iteration reports.
#[derive(Clone)]
pub struct Control {
    /// Worker threads (`None`: rayon default).
    pub threads: Option<usize>,
    /// Set to stop early (e.g. by a Ctrl-C handler); the best state so far is returned.
    pub stop: Arc<AtomicBool>,
    /// Progress of the pre-estimation and the joint iterations.
    pub progress: Arc<dyn Progress>,
    /// Called after each iteration.
    pub on_iter: Option<IterCallback>,
}

impl Default for Control {
    fn default() -> Self {
        Control { threads: None, stop: Arc::new(AtomicBool::new(false)), progress: Arc::new(NoProgress), on_iter: None }
    }
}

impl std::fmt::Debug for Control {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Control")
            .field("threads", &self.threads)
            .field("stop", &self.stop)
            .field("on_iter", &self.on_iter.is_some())
            .finish_non_exhaustive()
    }
}

/// Options of [`super::fit`].
#[derive(Clone, Debug, Default)]
pub struct FitOptions {
    /// Preparation, grid and fixed pattern.
    pub input: InputOptions,
    /// Fit renders and loss.
    pub render: RenderSettings,
    /// Pre-estimation.
    pub pre: PreOptions,
    /// Joint optimization.
    pub joint: JointOptions,
    /// Finish.
    pub finish: FinishOptions,
    /// Threads, stop flag, progress, per-iteration callback.
    pub control: Control,
}

impl FitOptions {
    /// Fast settings (tests, demo, eval): smaller renders (10 px per cell).
    pub fn fast() -> Self {
        let mut o = FitOptions::default();
        o.render.px_per_cell = 10;
        o
    }

    /// Whether the options can run: cells of at least 2 px, at least 1 sample per pixel, and a
    /// fixed pattern that is a weave (the fitted parameter file must be one, see
    /// [`crate::params::ParamFile::validate`]; refused here rather than after the fit).
    pub fn validate(&self) -> Result<()> {
        if self.render.px_per_cell < 2 || self.pre.px_per_cell == 1 || self.render.spp == 0 || self.pre.spp == 0 {
            bail!("px_per_cell must be ≥ 2 and spp ≥ 1");
        }
        if let Some(p) = &self.input.pattern {
            p.check_woven().context("the fixed pattern")?;
        }
        Ok(())
    }

    /// Whether the pattern's cells are estimated (no fixed pattern).
    pub fn cells_free(&self) -> bool {
        self.input.pattern.is_none()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_of_each_stage_and_fast_settings() {
        let d = FitOptions::default();
        assert!(d.input.prep && d.pre.enabled && d.finish.enabled && d.cells_free());
        assert_eq!((d.render.px_per_cell, d.render.spp, d.render.loss_block), (16, 4, 2));
        assert_eq!((d.joint.iterations, d.joint.t0, d.joint.decay), (30, anneal::T0, anneal::DECAY));
        assert_eq!(d.joint.accept0, anneal::ACCEPT0);
        assert!(!d.joint.plateau_stop, "the plateau stop is opt-in");
        let f = FitOptions::fast();
        assert_eq!(f.render.px_per_cell, 10);
        assert_eq!(f.joint.iterations, d.joint.iterations);
        f.validate().unwrap();
    }

    #[test]
    fn validation_refuses_one_pixel_cells_and_zero_samples() {
        let mut o = FitOptions::default();
        o.render.px_per_cell = 1;
        assert!(o.validate().is_err());
        let mut o = FitOptions::default();
        o.pre.spp = 0;
        assert!(o.validate().is_err());
        let mut o = FitOptions::default();
        o.pre.px_per_cell = 1;
        assert!(o.validate().unwrap_err().to_string().contains("px_per_cell"));
        // A fixed pattern with a yarn floating over the whole repeat cannot give a weave.
        let mut o = FitOptions::default();
        o.input.pattern = Some(WeavePattern::parse("110/011/000").unwrap());
        assert!(format!("{:#}", o.validate().unwrap_err()).contains("not woven"));
        o.input.pattern = Some(WeavePattern::preset("twill22").unwrap());
        o.validate().unwrap();
    }

    #[test]
    fn mode_parses_from_its_name() {
        assert_eq!("joint".parse::<FitMode>().unwrap(), FitMode::Joint);
        assert_eq!("separate".parse::<FitMode>().unwrap(), FitMode::Separate);
        assert!("both".parse::<FitMode>().unwrap_err().to_string().contains("joint, separate"));
    }
}
