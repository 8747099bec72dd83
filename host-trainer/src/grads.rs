//! Gradients as burn keeps them (`GradientsParams`, keyed by parameter id), walked with
//! module visitors: the global norm and its clip (PyTorch's `clip_grad_norm_`), flattening
//! for diagnostics, and moving or mixing the gradients of two copies of one network (the
//! two threads of a minibatch in the recurrent warm start, the int8-grid copy of the
//! quantisation-aware one).

use crate::model::values;
use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Tensor, TensorData};

/// Sums the squares of the gradients of a module's parameters.
struct SquaredNorm<'a> {
    grads: &'a GradientsParams,
    sum: f64,
}

impl ModuleVisitor for SquaredNorm<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.get::<D>(param.id) {
            self.sum += f64::from(g.square().sum().into_scalar::<f32>());
        }
    }
}

/// Scales the gradients of a module's parameters.
struct Scale<'a> {
    grads: &'a mut GradientsParams,
    factor: f32,
}

impl ModuleVisitor for Scale<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.remove::<D>(param.id) {
            self.grads.register(param.id, g.mul_scalar(self.factor));
        }
    }
}

/// Collects the gradients of a module's parameters, flattened in visiting order.
struct Flatten<'a> {
    grads: &'a GradientsParams,
    out: Vec<f32>,
}

impl ModuleVisitor for Flatten<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.get::<D>(param.id) {
            self.out.extend(values(g));
        }
    }
}

/// The gradients of `module`'s parameters, flattened in visiting order.
pub fn flatten_gradients<M: Module>(module: &M, grads: &GradientsParams) -> Vec<f32> {
    let mut v = Flatten {
        grads,
        out: Vec::new(),
    };
    module.visit(&mut v);
    v.out
}

/// `grads` of `from`'s parameters, registered under the ids of `to`'s (a copy of `from`
/// with the same structure and fresh parameter ids), matched in visiting order.
pub fn transfer_gradients<M: Module>(from: &M, grads: GradientsParams, to: &M) -> GradientsParams {
    struct Take {
        grads: GradientsParams,
        taken: Vec<Option<Vec<f32>>>,
    }
    impl ModuleVisitor for Take {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let g = self.grads.remove::<D>(param.id);
            self.taken.push(g.map(values));
        }
    }
    struct Give {
        taken: std::vec::IntoIter<Option<Vec<f32>>>,
        out: GradientsParams,
    }
    impl ModuleVisitor for Give {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(Some(g)) = self.taken.next() {
                let v = param.val();
                let t = Tensor::<D>::from_data(TensorData::new(g, v.dims()), &v.device());
                self.out.register(param.id, t);
            }
        }
    }
    let mut take = Take {
        grads,
        taken: Vec::new(),
    };
    from.visit(&mut take);
    let mut give = Give {
        taken: take.taken.into_iter(),
        out: GradientsParams::new(),
    };
    to.visit(&mut give);
    give.out
}

/// `wa · a + wb · b` for every parameter of `module` (gradients of two parts of one
/// minibatch, computed apart).
pub fn weighted_sum<M: Module>(
    module: &M,
    a: GradientsParams,
    wa: f32,
    b: GradientsParams,
    wb: f32,
) -> GradientsParams {
    struct Sum {
        a: GradientsParams,
        b: GradientsParams,
        out: GradientsParams,
        wa: f32,
        wb: f32,
    }
    impl ModuleVisitor for Sum {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let g = match (self.a.remove::<D>(param.id), self.b.remove::<D>(param.id)) {
                (Some(x), Some(y)) => Some(x.mul_scalar(self.wa) + y.mul_scalar(self.wb)),
                (Some(x), None) => Some(x.mul_scalar(self.wa)),
                (None, Some(y)) => Some(y.mul_scalar(self.wb)),
                (None, None) => None,
            };
            if let Some(g) = g {
                self.out.register(param.id, g);
            }
        }
    }
    let mut v = Sum {
        a,
        b,
        out: GradientsParams::new(),
        wa,
        wb,
    };
    module.visit(&mut v);
    v.out
}

/// The sum of the squares of `grads` over `module`'s parameters (the squared global norm).
pub fn squared_norm<M: Module>(module: &M, grads: &GradientsParams) -> f64 {
    let mut v = SquaredNorm { grads, sum: 0.0 };
    module.visit(&mut v);
    v.sum
}

/// Multiplies `grads` of `module`'s parameters by `factor`.
pub fn scale<M: Module>(module: &M, grads: &mut GradientsParams, factor: f32) {
    let mut v = Scale { grads, factor };
    module.visit(&mut v);
}
