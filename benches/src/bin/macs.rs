//! Prints the MAC count and weight bytes of every stage of the named configurations:
//! `cargo run -p scdp-benches --release --bin macs [metaworld|panda|tiny ...]`.

use scdp_benches::macs::{by_stage, frame_layers, step_layers, totals};
use scdp_engine::ModelConfig;

const MB: f64 = 1e6;

fn print_config(name: &str, config: &ModelConfig) {
    let steps = config.num_inference_steps;
    let frames = config.n_obs_steps;
    println!(
        "\n{name}: {}x{} frames x{frames}, {steps} denoising steps",
        config.image_width, config.image_height
    );
    println!(
        "| stage | runs | MMAC per run | MB weights f32 | MB weights int8 | share of end to end |"
    );
    println!("|---|---|---:|---:|---:|---:|");
    let totals = totals(config);
    let end_to_end = totals.end_to_end_macs as f64;
    let print_rows = |layers: &[scdp_benches::macs::Layer], runs: u32, per: &str| {
        for row in by_stage(layers) {
            println!(
                "| {} | {runs} per {per} | {:.2} | {:.2} | {:.2} | {:.1}% |",
                row.stage.label(),
                row.macs as f64 / 1e6,
                4.0 * row.weights as f64 / MB,
                row.weights as f64 / MB,
                100.0 * (runs as u64 * row.macs) as f64 / end_to_end
            );
        }
    };
    print_rows(&frame_layers(config), frames, "inference (1 per frame)");
    print_rows(&step_layers(config), steps, "inference (1 per step)");
    println!(
        "| **one frame** | | {:.1} | {:.2} | {:.2} | |",
        totals.frame_macs as f64 / 1e6,
        4.0 * totals.frame_weights as f64 / MB,
        totals.frame_weights as f64 / MB
    );
    println!(
        "| **one denoising step** | | {:.2} | {:.2} | {:.2} | |",
        totals.step_macs as f64 / 1e6,
        4.0 * totals.step_weights as f64 / MB,
        totals.step_weights as f64 / MB
    );
    println!(
        "| **end to end** ({frames} frames + {steps} steps) | | {:.1} | | | 100% |",
        end_to_end / 1e6
    );
    println!(
        "| **streaming** (newest frame + {steps} steps) | | {:.1} | | | |",
        totals.streaming_macs as f64 / 1e6
    );
}

fn main() {
    let mut names: Vec<String> = std::env::args().skip(1).collect();
    if names.is_empty() {
        names = vec!["metaworld".into(), "panda".into()];
    }
    for name in names {
        let config = match name.as_str() {
            "metaworld" => ModelConfig::METAWORLD,
            "panda" => ModelConfig::PANDA,
            "tiny" => ModelConfig::TINY,
            other => {
                eprintln!("unknown configuration {other}: metaworld, panda or tiny");
                std::process::exit(2);
            }
        };
        print_config(&name, &config);
    }
}
