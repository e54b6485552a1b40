//! `shotpilot-sim`: run the simulated vehicle and camera.
fn main() {
    println!("shotpilot-sim {}", env!("CARGO_PKG_VERSION"));
}
