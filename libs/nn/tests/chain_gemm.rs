//! The chain GEMM installed over ATen's CPU matrix products (`rlmflow_nn::libtorch::pin_gemm`),
//! as a model stage's process has it under the portable pins: a model's forward and backward
//! passes give the same bits at every width this CPU runs and on 1 or 2 threads, each product is the chain kernel's,
//! other dtypes keep ATen's kernels, and unsetting the variable restores them. One test: the
//! installation and the variables are the process's.

use rlmflow_nn::libtorch::{chain_lanes_widest, chain_mm, pin_gemm};
use rlmflow_nn::transformer::attend;
use rlmflow_stages::numerics::{ATTENTION_BY_PRODUCTS, ATTENTION_VARIABLE, CHAIN_GEMM, GEMM_LANES_VARIABLE, GEMM_VARIABLE};
use tch::{Device, Kind, Tensor, nn, nn::Module};

fn set(var: &str, value: Option<&str>) {
    // SAFETY: the only test of this binary; no other thread reads the environment.
    unsafe {
        match value {
            Some(v) => std::env::set_var(var, v),
            None => std::env::remove_var(var),
        }
    }
}

fn bits(t: &Tensor) -> Vec<u32> {
    Vec::<f32>::try_from(t.detach().contiguous().flatten(0, -1)).unwrap().iter().map(|v| v.to_bits()).collect()
}

/// A linear layer on a batch of sequences, attention scores (`matmul` of 4-D tensors, ATen's
/// `bmm`), causal attention by its products (`RLMFLOW_ATTENTION=products`), `addmm` with a bias,
/// `baddbmm` with other coefficients, and the gradients of the weights: every float32 product a
/// model stage's step makes, each as bits.
fn model_products() -> Vec<Vec<u32>> {
    tch::manual_seed(11);
    let vs = nn::VarStore::new(Device::Cpu);
    let linear = nn::linear(vs.root() / "l", 48, 40, Default::default());
    let x = Tensor::randn([6, 37, 48], (Kind::Float, Device::Cpu));
    let y = linear.forward(&x);
    let q = y.view([6, 37, 4, 10]).transpose(1, 2);
    let scores = q.matmul(&q.transpose(-2, -1));
    let attended = attend(&q, &q, &q, true);
    let r = |shape: &[i64]| Tensor::randn(shape, (Kind::Float, Device::Cpu));
    let biased = r(&[7]).addmm(&r(&[5, 300]), &r(&[300, 7]));
    let mixed = r(&[3, 5, 7]).baddbmm(&r(&[3, 5, 300]), &r(&[3, 300, 7]), 0.5, 2.0);
    (scores.sum(Kind::Float) + attended.sum(Kind::Float)).backward();
    let mut out = vec![bits(&y), bits(&scores), bits(&attended), bits(&biased), bits(&mixed)];
    out.extend(vs.trainable_variables().iter().map(|v| bits(&v.grad())));
    out
}

#[test]
fn installed_the_chain_gemm_computes_every_product_alike_at_every_width_and_unset_restores_aten() {
    set(ATTENTION_VARIABLE, Some(ATTENTION_BY_PRODUCTS));
    set(GEMM_VARIABLE, None);
    set(GEMM_LANES_VARIABLE, None);
    assert_eq!(pin_gemm().unwrap(), 0);
    let aten = model_products();
    let doubles = (Tensor::randn([30, 40], (Kind::Double, Device::Cpu)), Tensor::randn([40, 20], (Kind::Double, Device::Cpu)));
    let aten_doubles = doubles.0.mm(&doubles.1);

    set(GEMM_VARIABLE, Some(CHAIN_GEMM));
    assert_eq!(pin_gemm().unwrap(), chain_lanes_widest(), "the widest lanes unless asked");
    let widest = model_products();
    let (a, b) = (Tensor::randn([20, 8320], (Kind::Float, Device::Cpu)), Tensor::randn([8320, 40], (Kind::Float, Device::Cpu)));
    assert_eq!(bits(&a.mm(&b)), bits(&chain_mm(&a, &b, 1).unwrap()), "an installed `mm` is the chain kernel");
    assert_eq!(bits(&a.matmul(&b.tr().contiguous().tr())), bits(&chain_mm(&a, &b, 1).unwrap()));
    assert!(doubles.0.mm(&doubles.1).equal(&aten_doubles), "float64 keeps ATen's kernel");

    for lanes in [1, 8, 16].into_iter().filter(|&l| l <= chain_lanes_widest()) {
        set(GEMM_LANES_VARIABLE, Some(&lanes.to_string()));
        assert_eq!(pin_gemm().unwrap(), lanes);
        assert!(model_products() == widest, "{lanes} lanes computed other bits than {}", chain_lanes_widest());
    }
    set(GEMM_LANES_VARIABLE, None);
    pin_gemm().unwrap();
    for threads in [1, 2] {
        tch::set_num_threads(threads);
        let got = model_products();
        let differ: Vec<usize> = (0..got.len()).filter(|&i| got[i] != widest[i]).collect();
        assert!(got == widest, "{threads} threads computed other bits: {differ:?}");
    }
    if chain_lanes_widest() < 16 {
        eprintln!("this CPU has no AVX-512: the 16-lane kernel is compared where a CPU has it");
    }

    set(GEMM_LANES_VARIABLE, Some("4"));
    let wrong = pin_gemm().unwrap_err().to_string();
    assert!(wrong.contains("RLMFLOW_GEMM_LANES=4") && wrong.contains("1, 8 or 16"), "{wrong}");
    set(GEMM_LANES_VARIABLE, None);
    set(GEMM_VARIABLE, Some("mkl"));
    let wrong = pin_gemm().unwrap_err().to_string();
    assert!(wrong.contains("RLMFLOW_GEMM=mkl") && wrong.contains(CHAIN_GEMM), "{wrong}");

    set(GEMM_VARIABLE, None);
    assert_eq!(pin_gemm().unwrap(), 0);
    assert!(model_products() == aten, "unset, ATen's kernels are back");
}
