//! Sets `cfg(shared_data)` when the project's shared datasets (`../shared/data` beside the
//! checkout) are present, so the tests that need them are marked ignored, with the reason, in
//! a plain clone's `cargo test` output instead of passing silently.

fn main() {
    let shared = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    println!("cargo::rustc-check-cfg=cfg(shared_data)");
    if shared.is_dir() {
        println!("cargo::rerun-if-changed={}", shared.display());
        println!("cargo::rustc-cfg=shared_data");
    } else {
        // A path that does not exist counts as changed on every build, so watching the missing
        // folder made cargo compile the library again on every command in a plain clone.
        // Without the data only a change of this script reruns it (after adding the data:
        // `touch crates/mrfmap/build.rs`).
        println!("cargo::rerun-if-changed=build.rs");
    }
}
