//! The network: a fully convolutional VGG-style backbone that pools pixels down to one feature
//! vector per pattern cell, a 1×1-conv head with one over/under logit per cell, and a small
//! parameter head with a mean and a log-variance per output.
//!
//! ```text
//! input (B,4,H,W), H and W multiples of px_per_cell = 2^K
//!   block k = 0..K: [conv3×3 (+ GroupNorm) + LeakyReLU] × convs_per_block  →  max-pool 2
//!                   (H/2^K = cells)
//!   cell convs:     [conv3×3, dilation d_j (+ GroupNorm) + LeakyReLU] per entry of cell_convs,
//!                   optionally residual (h + f(h)) after the first, where the channels agree
//!                   (a cell sees its neighbours up to Σ d_j cells away)
//!   cell head:      conv1×1 → (B,1,h,w) logits: > 0 means the horizontal yarn (weft) is on top
//!   parameter head: spatial mean ‖ max of the cell features → fc (hidden) → LeakyReLU →
//!                   (mean = sigmoid, log-variance clamped to [−12, 2]) per output
//! ```
//!
//! Being fully convolutional, the network reads a view of any number of cells: the fit's repeat
//! tiled to at least the training views' 8 × 8 cells. Variable names (safetensors keys):
//! `block{k}.conv{j}`, `cell{j}`, `cell_head`, `fc1`, `head` (each `.weight`, `.bias`), and with
//! group normalisation `block{k}.norm{j}`, `cellnorm{j}` (each `.scale`, `.shift`). Use
//! [`seeded_init`] after building: candle's own initialisers are not seedable.
//!
//! Group normalisation (Wu & He 2018, "Group Normalization"; [`NetSpec::norm_group_size`] > 0)
//! normalises each sample's activations over groups of channels and all pixels, so training and
//! inference compute the same function (no running statistics as in batch normalisation, whose
//! batch-of-32 estimates would differ from the one-view inference pass).

use super::{NetSpec, INPUT_CHANNELS};
use candle_core::{DType, Device, Module, Result, Tensor};
use candle_nn::{conv2d, linear, ops, Conv2d, Conv2dConfig, Linear, VarBuilder, VarMap};
use rand::prelude::*;

/// Range of the predicted log-variance (of range-normalised values): σ from 0.0025 to 2.7 of the
/// range. The floor keeps the likelihood from rewarding ever smaller variances on outputs the
/// network already fits to float noise.
pub const LOG_VAR_RANGE: (f64, f64) = (-12.0, 2.0);

/// The pre-estimator network. Build it with [`PreNet::new`] from a [`VarBuilder`] over a
/// [`VarMap`] (training) and overwrite the weights with [`seeded_init`] or loaded values.
#[derive(Debug)]
pub struct PreNet {
    spec: NetSpec,
    blocks: Vec<Vec<(Conv2d, Option<GroupNorm>)>>,
    cell: Vec<(Conv2d, Option<GroupNorm>)>,
    cell_head: Conv2d,
    fc1: Option<Linear>,
    head: Option<Linear>,
}

/// Output of [`PreNet::forward`].
#[derive(Debug)]
pub struct NetOutput {
    /// Over/under logit per cell, `(B, H/px_per_cell, W/px_per_cell)`.
    pub cell_logits: Tensor,
    /// Range-normalised means in `(0,1)`, `(B, n_outputs)`; `None` without outputs.
    pub mean: Option<Tensor>,
    /// Log-variances of the normalised values, `(B, n_outputs)`; `None` without outputs.
    pub log_var: Option<Tensor>,
}

impl PreNet {
    /// Build the layers (variables are created in `vb`).
    pub fn new(spec: &NetSpec, vb: VarBuilder) -> Result<Self> {
        let pad = Conv2dConfig { padding: 1, ..Default::default() };
        let mut blocks = Vec::new();
        let mut cin = INPUT_CHANNELS + if spec.orientation_channels { 2 } else { 0 };
        for (k, &c) in spec.backbone.iter().enumerate() {
            let mut convs = Vec::new();
            for j in 0..spec.convs_per_block {
                let conv = conv2d(cin, c, 3, pad, vb.pp(format!("block{k}.conv{j}")))?;
                convs.push((conv, GroupNorm::new(spec, c, vb.pp(format!("block{k}.norm{j}")))?));
                cin = c;
            }
            blocks.push(convs);
        }
        if spec.cell_cues {
            cin += CELL_CUES;
        }
        let mut cell = Vec::new();
        for (j, &c) in spec.cell_convs.iter().enumerate() {
            let d = spec.cell_dilation(j);
            let dilated = Conv2dConfig { padding: d, dilation: d, ..Default::default() };
            let conv = conv2d(cin, c, 3, dilated, vb.pp(format!("cell{j}")))?;
            cell.push((conv, GroupNorm::new(spec, c, vb.pp(format!("cellnorm{j}")))?));
            cin = c;
        }
        let cell_head = conv2d(cin, 1, 1, Conv2dConfig::default(), vb.pp("cell_head"))?;
        let (fc1, head) = if spec.n_outputs() > 0 {
            (
                Some(linear(2 * cin, spec.hidden, vb.pp("fc1"))?),
                Some(linear(spec.hidden, 2 * spec.n_outputs(), vb.pp("head"))?),
            )
        } else {
            (None, None)
        };
        Ok(Self { spec: spec.clone(), blocks, cell, cell_head, fc1, head })
    }

    /// The spec this network was built from.
    pub fn spec(&self) -> &NetSpec {
        &self.spec
    }

    /// Forward pass on a batch `(B, 4, H, W)` of preprocessed views (H, W multiples of
    /// `px_per_cell`).
    pub fn forward(&self, x: &Tensor) -> Result<NetOutput> {
        // LeakyReLU throughout: with plain ReLUs the trunk died within the first epoch on the
        // rendered views (every unit of the last layer negative, the cell loss stuck at ln 2 for
        // any learning rate from 3e-4 to 1e-2), and a dead unit never recovers.
        let s = self.spec.leaky_slope;
        let leaky = |t: Tensor| -> Result<Tensor> { (t.relu()? * (1.0 - s))? + (t * s)? };
        let mut h = if self.spec.orientation_channels { with_orientation_channels(x)? } else { x.clone() };
        let cues = if self.spec.cell_cues { Some(cell_cues(&h, self.spec.px_per_cell)?) } else { None };
        let layer = |h: &Tensor, (conv, norm): &(Conv2d, Option<GroupNorm>)| -> Result<Tensor> {
            let z = h.apply(conv)?;
            leaky(match norm {
                Some(n) => n.forward(&z)?,
                None => z,
            })
        };
        for convs in &self.blocks {
            for l in convs {
                h = layer(&h, l)?;
            }
            h = max_pool2(&h)?;
        }
        if let Some(c) = &cues {
            h = Tensor::cat(&[&h, c], 1)?;
        }
        for (j, l) in self.cell.iter().enumerate() {
            let f = layer(&h, l)?;
            h = if self.spec.cell_residual && j > 0 && f.dims() == h.dims() { (h + f)? } else { f };
        }
        let cell_logits = h.apply(&self.cell_head)?.squeeze(1)?;
        let (mut mean, mut log_var) = (None, None);
        if let (Some(fc1), Some(head)) = (&self.fc1, &self.head) {
            let (b, c, hh, ww) = h.dims4()?;
            let flat = h.reshape((b, c, hh * ww))?;
            let pooled = Tensor::cat(&[flat.mean(2)?, flat.max(2)?], 1)?;
            let z = leaky(fc1.forward(&pooled)?)?;
            let out = head.forward(&z)?;
            let n = self.spec.n_outputs();
            mean = Some(ops::sigmoid(&out.narrow(1, 0, n)?)?);
            log_var = Some(out.narrow(1, n, n)?.clamp(LOG_VAR_RANGE.0, LOG_VAR_RANGE.1)?);
        }
        Ok(NetOutput { cell_logits, mean, log_var })
    }
}

/// 2 × 2 max-pooling whose backward pass is right.
///
/// candle 0.11's `max_pool2d` backward multiplies the upsampled gradient by the *share* of maxima
/// in each window (`avg_pool` of the arg-max mask, ¼ for a unique maximum) where it should divide
/// by their count: every pooling scales the gradient of all the layers before it by ¼ (measured:
/// the trunk's first block got 1/16 of its finite-difference gradient through two pools; test
/// `gradients_of_the_dilated_residual_stack_match_finite_differences`). Adam's per-weight
/// normalisation hides most of that, but not its ε nor the balance between the pooled trunk and
/// the layers after it. `p̂ + 4 (p − p̂)`, with `p̂` the detached pool, has the value `p` exactly
/// (`p − p̂` is 0) and 4 × candle's gradient, i.e. the whole gradient at a unique maximum.
fn max_pool2(h: &Tensor) -> Result<Tensor> {
    let p = h.max_pool2d(2)?;
    let fixed = p.detach();
    &fixed + ((&p - &fixed)? * 4.0)?
}

/// `x` with two more planes, `|∂I/∂x|` and `|∂I/∂y|` of the mean `I` of its three colour
/// planes (central differences on the edge-replicated plane, per pixel).
///
/// Why: whether the weft or the warp is on top of a cell shows as the orientation of the
/// intensity changes inside it — a horizontal yarn on top varies along y and hardly along x, a
/// vertical one the other way round (the orientation energy of classic texture analysis, e.g.
/// the structure tensor of Bigün & Granlund 1987). Given these planes, the first layer does not
/// have to discover derivative filters before the cell loss can leave ln 2. Computed inside the
/// network so that the dihedral augmentation (a transpose swaps the two planes) and inference
/// need no special handling.
fn with_orientation_channels(x: &Tensor) -> Result<Tensor> {
    let lum = x.narrow(1, 0, 3)?.mean_keepdim(1)?;
    let padded = lum.pad_with_same(2, 1, 1)?.pad_with_same(3, 1, 1)?;
    let (_, _, h, w) = lum.dims4()?;
    let gx = ((padded.narrow(2, 1, h)?.narrow(3, 2, w)? - padded.narrow(2, 1, h)?.narrow(3, 0, w)?)? * 0.5)?;
    let gy = ((padded.narrow(2, 2, h)?.narrow(3, 1, w)? - padded.narrow(2, 0, h)?.narrow(3, 1, w)?)? * 0.5)?;
    Tensor::cat(&[x, &gx.abs()?, &gy.abs()?], 1)
}

/// Planes [`cell_cues`] adds at cell resolution.
const CELL_CUES: usize = 2;

/// Per cell of `px` × `px` pixels, from the two orientation planes of
/// `with_orientation_channels` (channels 4 and 5 of `x`), their cell means `gx`, `gy` turned into
/// `ln((gy + ε) / (gx + ε))` (> 0: the intensity changes mostly along y, as across a weft lying
/// on top) and `ln(gx + gy + ε)` (how much texture there is to judge by), `(B, 2, H/px, W/px)`.
///
/// Why: fed beside the trunk's features into the layers at cell resolution, the cell head has a
/// linear cue for over/under from the first step. Measured (session 9, examples/net_diag `cue`):
/// the sign of this ratio alone reads 55 % of the grid cells of the default set right (61 %
/// front-lit), so it is a weak cue, and a first epoch with it stayed at chance like without.
fn cell_cues(x: &Tensor, px: usize) -> Result<Tensor> {
    const EPS: f64 = 0.01;
    let g = x.narrow(1, INPUT_CHANNELS, 2)?.avg_pool2d(px)?;
    let (gx, gy) = ((g.narrow(1, 0, 1)? + EPS)?, (g.narrow(1, 1, 1)? + EPS)?);
    let ratio = (gy.log()? - gx.log()?)?;
    let strength = (gx + gy)?.log()?;
    Tensor::cat(&[&ratio, &strength], 1)
}

/// Group normalisation of a `(B, C, H, W)` activation (Wu & He 2018): the channels are split
/// into `C / group_size` groups and each sample's group is standardised over its channels and
/// pixels, `ŷ = (y − μ) / √(σ² + ε)`, then scaled and shifted per channel, `γ_c ŷ + β_c`.
#[derive(Debug)]
struct GroupNorm {
    groups: usize,
    scale: Tensor,
    shift: Tensor,
}

/// ε of [`GroupNorm`]: keeps a constant group (zero variance) finite.
const GN_EPS: f64 = 1e-5;

impl GroupNorm {
    /// The layer for `channels` channels when the spec asks for normalisation, else `None`.
    fn new(spec: &NetSpec, channels: usize, vb: VarBuilder) -> Result<Option<Self>> {
        if spec.norm_group_size == 0 {
            return Ok(None);
        }
        let groups = (channels / spec.norm_group_size).max(1);
        let scale = vb.get_with_hints(channels, "scale", candle_nn::Init::Const(1.0))?;
        let shift = vb.get_with_hints(channels, "shift", candle_nn::Init::Const(0.0))?;
        Ok(Some(Self { groups, scale, shift }))
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let g = x.reshape((b, self.groups, (c / self.groups) * h * w))?;
        let mean = g.mean_keepdim(2)?;
        let centred = g.broadcast_sub(&mean)?;
        let var = centred.sqr()?.mean_keepdim(2)?;
        let normed = centred.broadcast_div(&(var + GN_EPS)?.sqrt()?)?.reshape((b, c, h, w))?;
        normed.broadcast_mul(&self.scale.reshape((1, c, 1, 1))?)?.broadcast_add(&self.shift.reshape((1, c, 1, 1))?)
    }
}

/// Loss terms of one batch.
#[derive(Debug)]
pub struct LossTerms {
    /// `bce + param_weight · nll`, the value that is minimised.
    pub total: Tensor,
    /// Mean binary cross-entropy of the cell logits.
    pub bce: f32,
    /// Mean Gaussian negative log-likelihood of the normalised outputs (without the constant
    /// ½ ln 2π; 0 without outputs).
    pub nll: f32,
}

/// Binary cross-entropy of the cell logits against `cells` (same shape, 0/1), plus
/// `param_weight` × the Gaussian negative log-likelihood `½(e^{−s}(μ − t)² + s)` of the
/// normalised `targets` `(B, n_outputs)` under mean `μ` and log-variance `s`, each term weighted
/// by its variance `e^s` held constant (β-NLL, β = 1).
pub fn loss(out: &NetOutput, cells: &Tensor, targets: &Tensor, param_weight: f64) -> Result<LossTerms> {
    // BCE with logits, in the stable form max(l, 0) − l·t + ln(1 + e^{−|l|}).
    let l = &out.cell_logits;
    let bce_t = ((l.relu()? - (l * cells)?)? + (l.abs()?.neg()?.exp()? + 1.0)?.log()?)?.mean_all()?;
    let bce = bce_t.to_scalar::<f32>()?;
    let (total, nll) = match (&out.mean, &out.log_var) {
        (Some(mu), Some(s)) => {
            let sq = (mu - targets)?.sqr()?;
            let per = (((s.neg()?.exp()? * sq)? + s)? * 0.5)?;
            let nll = per.mean_all()?.to_scalar::<f32>()?;
            // β-NLL with β = 1 (Seitzer et al. 2022, "On the pitfalls of heteroscedastic
            // uncertainty estimation"): each term weighted by its own variance, held constant.
            // The mean then gets the gradient of a squared error, not one scaled by 1/σ², which
            // otherwise grows as the variances shrink and swamps the cells' gradient in the shared
            // trunk; the variance's optimum (the squared error) is unchanged.
            let weighted = (per * s.exp()?.detach())?.mean_all()?;
            ((bce_t + (weighted * param_weight)?)?, nll)
        }
        _ => (bce_t, 0.0),
    };
    Ok(LossTerms { total, bce, nll })
}

/// Overwrite every variable of `varmap` deterministically from `seed`: biases and group-norm
/// shifts 0, group-norm scales 1, weights
/// He-uniform (`±√(6/fan_in)`), except the two heads (`±√(1/fan_in)`, so initial logits ≈ 0,
/// means ≈ 0.5 and log-variances ≈ 0). Variables are visited sorted by name so the result does
/// not depend on `HashMap` order.
pub fn seeded_init(varmap: &VarMap, seed: u64) -> Result<()> {
    let data = varmap.data().lock().expect("varmap lock poisoned");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = StdRng::seed_from_u64(seed);
    for name in names {
        let var = &data[name];
        let dims = var.dims().to_vec();
        let n: usize = dims.iter().product();
        let vals: Vec<f32> = if name.ends_with("bias") || name.ends_with(".shift") {
            vec![0.0; n]
        } else if name.ends_with(".scale") {
            vec![1.0; n]
        } else {
            let fan_in: usize = dims[1..].iter().product::<usize>().max(1);
            let small = name.starts_with("head.") || name.starts_with("cell_head.");
            let bound = if small { (1.0 / fan_in as f64).sqrt() } else { (6.0 / fan_in as f64).sqrt() } as f32;
            (0..n).map(|_| rng.random_range(-bound..bound)).collect()
        };
        var.set(&Tensor::from_vec(vals, dims, &Device::Cpu)?)?;
    }
    Ok(())
}

/// Names and shapes of all variables, sorted by name.
pub fn var_shapes(varmap: &VarMap) -> Vec<(String, Vec<usize>)> {
    let data = varmap.data().lock().expect("varmap lock poisoned");
    let mut v: Vec<(String, Vec<usize>)> = data.iter().map(|(k, var)| (k.clone(), var.dims().to_vec())).collect();
    v.sort();
    v
}

/// Build a fresh network (F32, CPU) with its variables in a new [`VarMap`], seeded.
pub fn build(spec: &NetSpec, seed: u64) -> Result<(VarMap, PreNet)> {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let net = PreNet::new(spec, vb)?;
    seeded_init(&varmap, seed)?;
    Ok((varmap, net))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::OutputSpec;

    fn spec() -> NetSpec {
        let mut s = NetSpec::new(16, vec![OutputSpec::continuous("x", 0.0, 1.0), OutputSpec::integer("n", 1, 7)]);
        (s.backbone, s.px_per_cell, s.cell_convs, s.hidden) = (vec![4, 8], 4, vec![8], 16);
        s
    }

    #[test]
    fn forward_shapes_and_ranges_for_any_number_of_cells() -> Result<()> {
        let mut with_cues = spec();
        (with_cues.orientation_channels, with_cues.cell_cues, with_cues.norm_group_size) = (true, true, 4);
        for ((h, w), s) in [(16, 16), (12, 20)].into_iter().flat_map(|d| [(d, spec()), (d, with_cues.clone())]) {
            let (_vm, net) = build(&s, 1)?;
            let x = Tensor::randn(0f32, 1.0, (5, 4, h, w), &Device::Cpu)?;
            let out = net.forward(&x)?;
            assert_eq!(out.cell_logits.dims(), &[5, h / 4, w / 4]);
            let m = out.mean.unwrap();
            assert_eq!(m.dims(), &[5, 2]);
            assert!(m.flatten_all()?.to_vec1::<f32>()?.iter().all(|&t| t > 0.0 && t < 1.0));
            let s = out.log_var.unwrap().flatten_all()?.to_vec1::<f32>()?;
            assert!(s.iter().all(|&v| (LOG_VAR_RANGE.0 as f32..=LOG_VAR_RANGE.1 as f32).contains(&v)));
        }
        Ok(())
    }

    /// Cell logits of a random 32 × 32 px, 4-channel input and of the same input with its corner
    /// 4 × 4 px (cell (0, 0) at 4 px per cell) raised by 3 in every channel.
    fn corner_cell_changed(net: &PreNet) -> Result<(Vec<f32>, Vec<f32>)> {
        let x = Tensor::randn(0f32, 1.0, (1, 4, 32, 32), &Device::Cpu)?;
        let mut v = x.flatten_all()?.to_vec1::<f32>()?;
        for c in 0..4 {
            for y in 0..4 {
                for xx in 0..4 {
                    v[c * 1024 + y * 32 + xx] += 3.0;
                }
            }
        }
        let y = Tensor::from_vec(v, (1, 4, 32, 32), &Device::Cpu)?;
        Ok((
            net.forward(&x)?.cell_logits.flatten_all()?.to_vec1::<f32>()?,
            net.forward(&y)?.cell_logits.flatten_all()?.to_vec1::<f32>()?,
        ))
    }

    #[test]
    fn cell_logits_are_local() -> Result<()> {
        // Changing the pixels of one corner cell must leave far cells' logits unchanged: the
        // receptive field of a cell is a few cells, not the image (translation equivariance).
        let s = spec();
        let (_vm, net) = build(&s, 2)?;
        let (a, b) = corner_cell_changed(&net)?;
        assert_ne!(a[0], b[0], "the changed cell's own logit must change");
        assert_eq!(a[63], b[63], "the opposite corner cell is out of reach");
        Ok(())
    }

    #[test]
    fn dilated_cell_convs_reach_further() -> Result<()> {
        // 32 × 32 px at 4 px per cell: 8 × 8 cells. Changing corner cell (0, 0) reaches, through
        // the trunk, cells 0–1 of row 0; two cell convs of dilation 1 add 2 cells (up to cell 3),
        // dilations 1 and 4 add 5 (up to cell 6). So cell (0, 5) must change only with the
        // dilated stack, with or without the residual connections.
        let corner_change = |dil: Vec<usize>, residual: bool| -> Result<(Vec<f32>, Vec<f32>)> {
            let mut s = spec();
            (s.cell_convs, s.cell_dilations, s.cell_residual) = (vec![8, 8], dil, residual);
            s.validate().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
            let (_vm, net) = build(&s, 3)?;
            corner_cell_changed(&net)
        };
        let (a, b) = corner_change(vec![], false)?;
        assert_ne!(a[3], b[3], "dilation 1: cell 3 is within reach");
        assert_eq!(a[4], b[4], "dilation 1: cell 4 is out of reach");
        for residual in [false, true] {
            let (a, b) = corner_change(vec![1, 4], residual)?;
            assert_ne!(a[5], b[5], "dilations 1, 4 (residual {residual}): cell 5 is within reach");
            assert_eq!(a[7], b[7], "dilations 1, 4 (residual {residual}): cell 7 is out of reach");
        }
        Ok(())
    }

    #[test]
    fn gradients_of_the_dilated_residual_stack_match_finite_differences() -> Result<()> {
        // candle's backward pass of a dilated conv (a dilated transposed conv for the input, a
        // strided conv for the kernel) checked against central differences of the cell loss
        // (`param_weight` 0: the β-NLL term's detached variance weight is not the loss's
        // derivative by design), for weights of the dilated cell conv, of the layer before it
        // (gradient through the dilated layer) and of both pooled blocks (gradient through one
        // and two max-pools: `max_pool2`; with candle's own backward these came out ¼ and 1/16 of
        // the finite differences).
        let mut s = spec();
        (s.cell_convs, s.cell_dilations, s.cell_residual) = (vec![8, 8], vec![1, 2], true);
        let (vm, net) = build(&s, 5)?;
        // Seeded input (candle's `randn` draws from the thread's RNG: a different batch each run).
        let mut rng = StdRng::seed_from_u64(9);
        let xs: Vec<f32> = (0..2 * 4 * 16 * 16).map(|_| rng.random_range(-1.5f32..1.5)).collect();
        let x = Tensor::from_vec(xs, (2, 4, 16, 16), &Device::Cpu)?;
        let cells =
            Tensor::from_vec((0..32).map(|i| (i % 3 == 0) as u8 as f32).collect::<Vec<_>>(), (2, 4, 4), &Device::Cpu)?;
        let t = Tensor::new(&[[0.2f32, 0.7], [0.6, 0.1]], &Device::Cpu)?;
        let total = || -> Result<f32> { loss(&net.forward(&x)?, &cells, &t, 0.0)?.total.to_scalar::<f32>() };
        let grads = loss(&net.forward(&x)?, &cells, &t, 0.0)?.total.backward()?;
        let data = vm.data().lock().unwrap();
        for (name, k) in
            [("cell1.weight", 40), ("cell0.weight", 100), ("block1.conv0.weight", 7), ("block0.conv0.weight", 7)]
        {
            let var = &data[name];
            let g = grads.get(var.as_tensor()).expect("a gradient").flatten_all()?.to_vec1::<f32>()?[k];
            let w0 = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
            let at = |d: f32| -> Result<f32> {
                let mut w = w0.clone();
                w[k] += d;
                var.set(&Tensor::from_vec(w, var.dims(), &Device::Cpu)?)?;
                total()
            };
            let h = 1e-3;
            let fd = (at(h)? - at(-h)?) / (2.0 * h);
            at(0.0)?;
            assert!((g - fd).abs() <= 0.05 * fd.abs().max(1e-3), "{name}[{k}]: backprop {g}, finite difference {fd}");
        }
        Ok(())
    }

    #[test]
    fn loss_matches_the_formulas() -> Result<()> {
        let d = &Device::Cpu;
        let out = NetOutput {
            cell_logits: Tensor::new(&[[[2.0f32, -1.0]]], d)?,
            mean: Some(Tensor::new(&[[0.3f32]], d)?),
            log_var: Some(Tensor::new(&[[-1.0f32]], d)?),
        };
        let cells = Tensor::new(&[[[1.0f32, 1.0]]], d)?;
        let t = Tensor::new(&[[0.5f32]], d)?;
        let l = loss(&out, &cells, &t, 2.0)?;
        let bce = ((1.0 + (-2.0f32).exp()).ln() + (1.0 + 1.0f32.exp()).ln()) / 2.0;
        let nll = 0.5 * (1.0f32.exp() * 0.04 - 1.0);
        assert!((l.bce - bce).abs() < 1e-5 && (l.nll - nll).abs() < 1e-5, "{l:?}");
        let beta = (-1.0f32).exp() * nll;
        assert!((l.total.to_scalar::<f32>()? - (bce + 2.0 * beta)).abs() < 1e-5);
        Ok(())
    }

    #[test]
    fn orientation_planes_follow_the_stripes() -> Result<()> {
        // Horizontal stripes two rows wide (rows 0 0 1 1 0 0 in every colour plane): |∂I/∂y| =
        // 0.5 on rows 1–4 (central difference across a stripe edge), 0 on the edge rows (their
        // replicated neighbour equals the inner one), and |∂I/∂x| = 0 everywhere; the input
        // planes pass through unchanged.
        let vals: Vec<f32> = (0..4 * 36).map(|i| if i < 108 { ((i % 36 / 12) % 2) as f32 } else { 0.3 }).collect();
        let x = Tensor::from_vec(vals.clone(), (1, 4, 6, 6), &Device::Cpu)?;
        let y = with_orientation_channels(&x)?;
        assert_eq!(y.dims(), &[1, 6, 6, 6]);
        let v = y.flatten_all()?.to_vec1::<f32>()?;
        assert_eq!(&v[..144], &vals[..]);
        assert!(v[144..180].iter().all(|&g| g == 0.0), "no change along x");
        for (k, g) in v[180..].iter().enumerate() {
            let want = if (1..5).contains(&(k / 6)) { 0.5 } else { 0.0 };
            assert!((g - want).abs() < 1e-6, "row {}: {g} vs {want}", k / 6);
        }
        Ok(())
    }

    #[test]
    fn cell_cues_say_which_way_the_cell_varies() -> Result<()> {
        // One 4 × 4 cell, orientation planes |∂x| = 0.09 and |∂y| = 0.39 everywhere: the cues are
        // ln(0.4 / 0.1) and ln(0.5).
        let mut v = vec![0.0f32; 6 * 16];
        v[64..80].fill(0.09);
        v[80..].fill(0.39);
        let x = Tensor::from_vec(v, (1, 6, 4, 4), &Device::Cpu)?;
        let c = cell_cues(&x, 4)?.flatten_all()?.to_vec1::<f32>()?;
        assert!((c[0] - 4.0f32.ln()).abs() < 1e-5 && (c[1] - 0.5f32.ln()).abs() < 1e-5, "{c:?}");
        Ok(())
    }

    #[test]
    fn group_norm_standardises_each_samples_groups() -> Result<()> {
        // 2 samples × 4 channels (2 groups of 2) × 3 × 3 px with very different levels and
        // spreads per sample and group: after the layer (scale 1, shift 0) every group of every
        // sample has mean 0 and variance 1 (up to ε).
        let mut s = spec();
        s.norm_group_size = 2;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let gn = GroupNorm::new(&s, 4, vb)?.expect("normalisation is on");
        assert_eq!(gn.groups, 2);
        let vals: Vec<f32> = (0..72).map(|i| (i % 7) as f32 * (1 + i / 18) as f32 + 10.0 * (i / 36) as f32).collect();
        let x = Tensor::from_vec(vals, (2, 4, 3, 3), &Device::Cpu)?;
        let y = gn.forward(&x)?.reshape((4, 18))?.to_vec2::<f32>()?;
        for g in &y {
            let m = g.iter().sum::<f32>() / 18.0;
            let v = g.iter().map(|t| (t - m).powi(2)).sum::<f32>() / 18.0;
            assert!(m.abs() < 1e-5 && (v - 1.0).abs() < 1e-3, "mean {m}, variance {v}");
        }
        // Without normalisation the spec builds no norm variables (models before session 9 load).
        let (vm, _) = build(&spec(), 1)?;
        assert!(var_shapes(&vm).iter().all(|(n, _)| !n.contains("norm")));
        let (vm, _) = build(&s, 1)?;
        let names: Vec<String> = var_shapes(&vm).into_iter().map(|v| v.0).collect();
        assert!(names.contains(&"block1.norm0.scale".to_string()) && names.contains(&"cellnorm0.shift".to_string()));
        let d = vm.data().lock().unwrap();
        assert_eq!(d["block0.norm0.scale"].as_tensor().to_vec1::<f32>()?, vec![1.0; 4], "seeded init: scale 1");
        Ok(())
    }

    #[test]
    fn seeded_init_is_deterministic() -> Result<()> {
        let s = spec();
        let dump = |vm: &VarMap| -> Vec<Vec<f32>> {
            let d = vm.data().lock().unwrap();
            let mut k: Vec<_> = d.keys().cloned().collect();
            k.sort();
            k.iter().map(|n| d[n].flatten_all().unwrap().to_vec1().unwrap()).collect()
        };
        let (a, _) = build(&s, 7)?;
        let (b, _) = build(&s, 7)?;
        let (c, _) = build(&s, 8)?;
        assert_eq!(dump(&a), dump(&b));
        assert_ne!(dump(&a), dump(&c));
        Ok(())
    }
}
