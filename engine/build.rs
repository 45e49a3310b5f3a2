//! `cfg(freestanding)`: set when the engine is built without its `std` feature, so code that
//! only exists for that build (reading the CPU's ID registers where there is no OS to ask)
//! is gated on what it is for rather than on the absence of a feature.
fn main() {
    println!("cargo::rustc-check-cfg=cfg(freestanding)");
    println!("cargo::rerun-if-changed=build.rs");
    if std::env::var_os("CARGO_FEATURE_STD").is_none() {
        println!("cargo::rustc-cfg=freestanding");
    }
}
