//! The no-adapter path for real: restrict wgpu to a backend this platform cannot have, and the
//! error must carry the install hint. Own test binary, because it sets a process-wide variable.

#[test]
fn missing_adapter_reports_install_hint() {
    // No other test runs in this binary, so nothing reads the environment concurrently.
    let backend = if cfg!(target_os = "macos") {
        "dx12"
    } else {
        "metal"
    };
    std::env::set_var("WGPU_BACKEND", backend);
    match strata_render::GpuContext::headless() {
        Ok(ctx) => panic!(
            "expected no adapter with WGPU_BACKEND={backend}, got {}",
            ctx.adapter_name()
        ),
        Err(e) => {
            let msg = e.to_string();
            assert!(
                msg.contains("apt-get install -y mesa-vulkan-drivers libvulkan1"),
                "{msg}"
            );
        }
    }
}
