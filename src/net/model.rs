//! The network: a VGG-style backbone, Gram and/or pooled features, two FC layers and the heads.
//!
//! ```text
//! input (B,3,S,S)
//!   block k = 0..K: [conv3×3 + ReLU] × convs_per_block  →  features of this block  →  max-pool 2
//! features: per block, upper triangle of the Gram matrix  G = F·Fᵀ / (H·W)   (C(C+1)/2 values)
//!           and/or spatial mean and max of each channel                      (2·C values),
//!           all passed through ln(1 + f) (they are ≥ 0 and span three decades)
//! fc1 (256) → LeakyReLU → fc2 (256) → LeakyReLU → head: class logits ‖ sigmoid(values)
//! ```
//!
//! Variable names (safetensors keys): `block{k}.conv{j}.{weight,bias}`, `fc1.*`, `fc2.*`, `head.*`.
//! Use [`seeded_init`] after building: candle's own initialisers are not seedable.

use super::{FeatureType, NetSpec};
use candle_core::{DType, Device, Module, Result, Tensor, D};
use candle_nn::{conv2d, linear, ops, Conv2d, Conv2dConfig, Linear, VarBuilder, VarMap};
use rand::prelude::*;

/// The pre-estimator network. Build it with [`PreNet::new`] from a [`VarBuilder`] over a
/// [`VarMap`] (training) and overwrite the weights with [`seeded_init`] or loaded values.
#[derive(Debug)]
pub struct PreNet {
    spec: NetSpec,
    blocks: Vec<Vec<Conv2d>>,
    /// Per block: indices of the upper triangle in the flattened `C×C` Gram matrix.
    triu: Vec<Tensor>,
    fc1: Linear,
    fc2: Linear,
    head: Linear,
}

/// Output of [`PreNet::forward`].
#[derive(Debug)]
pub struct NetOutput {
    /// Class logits `(B, n_classes)`, `None` when the spec has no classes.
    pub logits: Option<Tensor>,
    /// Range-normalised values in `(0,1)`, `(B, n_outputs)`, `None` when there are no outputs.
    pub values: Option<Tensor>,
}

/// Number of features fed to `fc1` for a spec.
pub fn feature_dim(spec: &NetSpec) -> usize {
    spec.backbone
        .iter()
        .map(|&c| match spec.features {
            FeatureType::Gram => c * (c + 1) / 2,
            FeatureType::Pooled => 2 * c,
            FeatureType::Both => c * (c + 1) / 2 + 2 * c,
        })
        .sum()
}

impl PreNet {
    /// Build the layers (variables are created in `vb`).
    pub fn new(spec: &NetSpec, vb: VarBuilder) -> Result<Self> {
        let cfg = Conv2dConfig { padding: 1, ..Default::default() };
        let mut blocks = Vec::new();
        let mut triu = Vec::new();
        let mut cin = 3;
        for (k, &c) in spec.backbone.iter().enumerate() {
            let mut convs = Vec::new();
            for j in 0..spec.convs_per_block {
                convs.push(conv2d(cin, c, 3, cfg, vb.pp(format!("block{k}.conv{j}")))?);
                cin = c;
            }
            blocks.push(convs);
            let idx: Vec<u32> = (0..c).flat_map(|i| (i..c).map(move |j| (i * c + j) as u32)).collect();
            triu.push(Tensor::from_vec(idx, c * (c + 1) / 2, vb.device())?);
        }
        let nf = feature_dim(spec);
        let fc1 = linear(nf, spec.hidden, vb.pp("fc1"))?;
        let fc2 = linear(spec.hidden, spec.hidden, vb.pp("fc2"))?;
        let head = linear(spec.hidden, spec.n_classes() + spec.n_outputs(), vb.pp("head"))?;
        Ok(Self { spec: spec.clone(), blocks, triu, fc1, fc2, head })
    }

    /// The spec this network was built from.
    pub fn spec(&self) -> &NetSpec {
        &self.spec
    }

    /// Feature vector `(B, feature_dim)` of a batch `(B,3,S,S)` of preprocessed images.
    pub fn features(&self, x: &Tensor) -> Result<Tensor> {
        let mut feats = Vec::new();
        let mut h = x.clone();
        for (k, convs) in self.blocks.iter().enumerate() {
            for conv in convs {
                h = h.apply(conv)?.relu()?;
            }
            let (b, c, hh, ww) = h.dims4()?;
            let flat = h.reshape((b, c, hh * ww))?;
            if matches!(self.spec.features, FeatureType::Gram | FeatureType::Both) {
                let g = flat.matmul(&flat.transpose(1, 2)?)?;
                let g = (g.reshape((b, c * c))? / (hh * ww) as f64)?;
                feats.push(g.index_select(&self.triu[k], 1)?);
            }
            if matches!(self.spec.features, FeatureType::Pooled | FeatureType::Both) {
                feats.push(flat.mean(2)?);
                feats.push(flat.max(2)?);
            }
            h = h.max_pool2d(2)?;
        }
        // All features are ≥ 0 (ReLU activations and their second moments) and grow with
        // depth and contrast (Gram entries reach 100+ at init): compress with ln(1 + f).
        (Tensor::cat(&feats, 1)? + 1.0)?.log()
    }

    /// Forward pass on a batch `(B,3,S,S)` of preprocessed images.
    pub fn forward(&self, x: &Tensor) -> Result<NetOutput> {
        let s = self.spec.leaky_slope;
        let leaky = |t: Tensor| -> Result<Tensor> { (t.relu()? * (1.0 - s))? + (t * s)? };
        let f = self.features(x)?;
        let h = leaky(self.fc1.forward(&f)?)?;
        let h = leaky(self.fc2.forward(&h)?)?;
        let out = self.head.forward(&h)?;
        let nc = self.spec.n_classes();
        let no = self.spec.n_outputs();
        let logits = if nc > 0 { Some(out.narrow(1, 0, nc)?) } else { None };
        let values = if no > 0 { Some(ops::sigmoid(&out.narrow(1, nc, no)?)?) } else { None };
        Ok(NetOutput { logits, values })
    }
}

/// Loss terms of one batch.
#[derive(Debug)]
pub struct LossTerms {
    /// `ce + l1_weight · l1`, the value that is minimised.
    pub total: Tensor,
    /// Mean cross-entropy of the classes (0 when there are fewer than 2 classes).
    pub ce: f32,
    /// Mean absolute error of the normalised values.
    pub l1: f32,
}

/// Cross-entropy on the class logits plus `l1_weight` × mean L1 on the normalised values.
/// `classes` is `(B,)` u32, `targets` `(B, n_outputs)` f32.
pub fn loss(out: &NetOutput, classes: &Tensor, targets: &Tensor, l1_weight: f64) -> Result<LossTerms> {
    let mut total: Option<Tensor> = None;
    let mut ce = 0.0;
    let mut l1 = 0.0;
    if let Some(logits) = &out.logits {
        if logits.dim(1)? > 1 {
            let t = candle_nn::loss::cross_entropy(logits, classes)?;
            ce = t.to_scalar::<f32>()?;
            total = Some(t);
        }
    }
    if let Some(values) = &out.values {
        let t = (values - targets)?.abs()?.mean_all()?;
        l1 = t.to_scalar::<f32>()?;
        let t = (t * l1_weight)?;
        total = Some(match total {
            Some(a) => (a + t)?,
            None => t,
        });
    }
    let total = match total {
        Some(t) => t,
        None => Tensor::new(0f32, classes.device())?,
    };
    Ok(LossTerms { total, ce, l1 })
}

/// Softmax probabilities of logits along the last dimension.
pub fn probabilities(logits: &Tensor) -> Result<Tensor> {
    ops::softmax(logits, D::Minus1)
}

/// Overwrite every variable of `varmap` deterministically from `seed`: biases 0, weights
/// He-uniform (`±√(6/fan_in)`), except the head (`±√(1/fan_in)`, so initial logits ≈ 0 and
/// values ≈ 0.5). Variables are visited sorted by name so the result does not depend on
/// `HashMap` order.
pub fn seeded_init(varmap: &VarMap, seed: u64) -> Result<()> {
    let data = varmap.data().lock().expect("varmap lock poisoned");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = StdRng::seed_from_u64(seed);
    for name in names {
        let var = &data[name];
        let dims = var.dims().to_vec();
        let n: usize = dims.iter().product();
        let vals: Vec<f32> = if name.ends_with("bias") {
            vec![0.0; n]
        } else {
            let fan_in: usize = dims[1..].iter().product::<usize>().max(1);
            let bound =
                if name.starts_with("head.") { (1.0 / fan_in as f64).sqrt() } else { (6.0 / fan_in as f64).sqrt() }
                    as f32;
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

    fn spec(features: FeatureType) -> NetSpec {
        let mut s = NetSpec::new(
            16,
            vec!["a".into(), "b".into(), "c".into()],
            vec![OutputSpec::continuous("x", 0.0, 1.0), OutputSpec::integer("n", 1, 7)],
        );
        s.backbone = vec![4, 8];
        s.hidden = 16;
        s.features = features;
        s
    }

    #[test]
    fn forward_shapes_and_ranges() -> Result<()> {
        for f in [FeatureType::Gram, FeatureType::Pooled, FeatureType::Both] {
            let s = spec(f);
            let (_vm, net) = build(&s, 1)?;
            let x = Tensor::randn(0f32, 1.0, (5, 3, 16, 16), &Device::Cpu)?;
            assert_eq!(net.features(&x)?.dims(), &[5, feature_dim(&s)]);
            let out = net.forward(&x)?;
            assert_eq!(out.logits.as_ref().unwrap().dims(), &[5, 3]);
            let v = out.values.unwrap();
            assert_eq!(v.dims(), &[5, 2]);
            for row in v.to_vec2::<f32>()? {
                assert!(row.iter().all(|&t| t > 0.0 && t < 1.0));
            }
        }
        Ok(())
    }

    #[test]
    fn gram_upper_triangle_matches_direct_computation() -> Result<()> {
        // With a 1-block Gram-only net, the features must equal ln(1 + Σ_p f_i(p) f_j(p) / (H·W)), i ≤ j.
        let mut s = spec(FeatureType::Gram);
        s.backbone = vec![3];
        s.input_size = 2;
        let (_vm, net) = build(&s, 3)?;
        let x = Tensor::randn(0f32, 1.0, (1, 3, 2, 2), &Device::Cpu)?;
        let f = net.features(&x)?.flatten_all()?.to_vec1::<f32>()?;
        let a = x.apply(&net.blocks[0][0])?.relu()?.flatten_all()?.to_vec1::<f32>()?;
        let mut k = 0;
        for i in 0..3 {
            for j in i..3 {
                let g: f32 = (0..4).map(|p| a[i * 4 + p] * a[j * 4 + p]).sum::<f32>() / 4.0;
                let g = g.ln_1p();
                assert!((g - f[k]).abs() < 1e-5, "({i},{j}): {g} vs {}", f[k]);
                k += 1;
            }
        }
        assert_eq!(k, f.len());
        Ok(())
    }

    #[test]
    fn seeded_init_is_deterministic() -> Result<()> {
        let s = spec(FeatureType::Both);
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
