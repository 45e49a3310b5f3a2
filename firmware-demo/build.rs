//! For the freestanding binary: generates the embedded model (seeded synthetic weights for
//! the tiny config, so no large file is committed) and links the binary without the C
//! runtime. Hosted builds need nothing from here.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    #[cfg(feature = "freestanding")]
    freestanding::prepare();
}

#[cfg(feature = "freestanding")]
mod freestanding {
    use std::path::PathBuf;

    use weights_tool::lowering::lower_to_weights_file;
    use weights_tool::synth::synth_state_dict;
    use weights_tool::{Quant, parse_config};

    /// Seed of the embedded model's synthetic weights.
    const SEED: u64 = 1;
    const BINARY: &str = "firmware-freestanding";
    /// `ModelConfig::TINY` as the workspace's config file; the binary checks the embedded
    /// model against the constant, so a drift between the two fails loudly.
    const TINY_TOML: &str = "../tests/configs/tiny.toml";

    pub fn prepare() {
        let out_dir = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
        println!("cargo:rerun-if-changed={TINY_TOML}");
        let text = std::fs::read_to_string(TINY_TOML)
            .unwrap_or_else(|error| panic!("reading {TINY_TOML}: {error}"));
        let config = parse_config(&text).unwrap_or_else(|error| panic!("{TINY_TOML}: {error}"));
        let state_dict = synth_state_dict(&config, SEED);
        let bytes = lower_to_weights_file(&config, &state_dict, Quant::F32)
            .unwrap_or_else(|error| panic!("generating the embedded tiny model: {error:#}"));
        let path = out_dir.join("tiny.scdp");
        std::fs::write(&path, bytes)
            .unwrap_or_else(|error| panic!("writing {}: {error}", path.display()));

        // No C runtime: the binary brings its own `_start`, and nothing from libc. Statically
        // linked and not position independent, so nothing has to relocate it at start-up.
        for argument in ["-nostartfiles", "-nostdlib", "-static", "-no-pie"] {
            println!("cargo:rustc-link-arg-bin={BINARY}={argument}");
        }
    }
}
