//! Open Image Denoise's `RT` filter through its C API (the `oidn` crate's `sys` bindings): the
//! crate's own wrapper cannot prefilter an auxiliary image alone, which `cleanAux` needs.

use oidn::sys::*;
use std::ffi::{CStr, c_char};
use std::sync::Mutex;
use tessera_film::Denoiser;

/// The most scratch memory one denoise may ask for; a larger frame is denoised in overlapping
/// tiles, slower but bounded (OIDN's `maxMemoryMB`).
const MAX_SCRATCH_MB: i32 = 1024;

/// Open Image Denoise on the CPU. One image at a time: a second caller waits, so a coordinator
/// finishing many frames at once holds one denoise's memory, not many.
pub struct Oidn {
    version: i32,
    one_at_a_time: Mutex<()>,
}

impl Oidn {
    /// Starts a CPU device once to check that the library and its CPU module load, and to read
    /// its version.
    pub fn start() -> Result<Self, String> {
        let device = Device::cpu()?;
        let version = unsafe { oidnGetDeviceInt(device.0, c"version".as_ptr()) };
        Ok(Oidn { version, one_at_a_time: Mutex::new(()) })
    }
}

impl Denoiser for Oidn {
    fn name(&self) -> String {
        let v = self.version;
        format!(
            "Open Image Denoise {}.{}.{} (RT filter, CPU, cleanAux with prefiltered albedo and normal)",
            v / 10000,
            v / 100 % 100,
            v % 100
        )
    }

    fn denoise(
        &self,
        width: u32,
        height: u32,
        color: &[[f32; 3]],
        albedo: &[[f32; 3]],
        normal: &[[f32; 3]],
    ) -> Result<Vec<[f32; 3]>, String> {
        let n = width as usize * height as usize;
        if [color.len(), albedo.len(), normal.len()] != [n; 3] {
            return Err(format!("the layers do not all hold {width}x{height} pixels"));
        }
        let _one = self.one_at_a_time.lock().unwrap_or_else(|e| e.into_inner());
        let device = Device::cpu()?;
        let size = (width as usize, height as usize);
        // OIDN's recommendation for final frames: denoise the auxiliary images first, then
        // the colour with `cleanAux`, which trusts them to be noise-free.
        let mut albedo = albedo.to_vec();
        let mut normal = normal.to_vec();
        device.run(size, &[(c"albedo", albedo.as_mut_ptr())], albedo.as_mut_ptr(), false)?;
        device.run(size, &[(c"normal", normal.as_mut_ptr())], normal.as_mut_ptr(), false)?;
        let mut out = vec![[0.0f32; 3]; n];
        // OIDN reads the inputs only; the pointer is mutable because the C API's is.
        let inputs =
            [(c"color", color.as_ptr().cast_mut()), (c"albedo", albedo.as_mut_ptr()), (c"normal", normal.as_mut_ptr())];
        device.run(size, &inputs, out.as_mut_ptr(), true)?;
        Ok(out)
    }
}

/// An OIDN device, released when dropped.
struct Device(OIDNDevice);

impl Device {
    fn cpu() -> Result<Self, String> {
        let raw = unsafe { oidnNewDevice(OIDNDeviceType_OIDN_DEVICE_TYPE_CPU) };
        if raw.is_null() {
            return Err("Open Image Denoise has no CPU device: is libOpenImageDenoise_device_cpu beside \
                        libOpenImageDenoise?"
                .into());
        }
        let device = Device(raw);
        unsafe { oidnCommitDevice(raw) };
        device.error()?;
        Ok(device)
    }

    /// The device's first error since the last call, as OIDN words it.
    fn error(&self) -> Result<(), String> {
        let mut message: *const c_char = std::ptr::null();
        let code = unsafe { oidnGetDeviceError(self.0, &mut message) };
        if code == OIDNError_OIDN_ERROR_NONE {
            return Ok(());
        }
        let said = if message.is_null() {
            String::new()
        } else {
            unsafe { CStr::from_ptr(message) }.to_string_lossy().into_owned()
        };
        Err(format!("Open Image Denoise: {said} (error {code})"))
    }

    /// Runs one `RT` filter over `inputs` (named images of float3 pixels) into `output`; `beauty`:
    /// the HDR colour with clean auxiliary images, else an auxiliary image prefiltered alone.
    fn run(
        &self,
        (width, height): (usize, usize),
        inputs: &[(&CStr, *mut [f32; 3])],
        output: *mut [f32; 3],
        beauty: bool,
    ) -> Result<(), String> {
        let filter = Filter(unsafe { oidnNewFilter(self.0, c"RT".as_ptr()) });
        if filter.0.is_null() {
            self.error()?;
            return Err("Open Image Denoise could not create its RT filter".into());
        }
        let image = |name: &CStr, data: *mut [f32; 3]| unsafe {
            oidnSetSharedFilterImage(
                filter.0,
                name.as_ptr(),
                data.cast(),
                OIDNFormat_OIDN_FORMAT_FLOAT3,
                width,
                height,
                0,
                0,
                0,
            )
        };
        for &(name, data) in inputs {
            image(name, data);
        }
        image(c"output", output);
        unsafe {
            if beauty {
                oidnSetFilterBool(filter.0, c"hdr".as_ptr(), true);
                oidnSetFilterBool(filter.0, c"cleanAux".as_ptr(), true);
            }
            oidnSetFilterInt(filter.0, c"maxMemoryMB".as_ptr(), MAX_SCRATCH_MB);
            oidnCommitFilter(filter.0);
        }
        self.error()?;
        unsafe { oidnExecuteFilter(filter.0) };
        self.error()
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        unsafe { oidnReleaseDevice(self.0) }
    }
}

/// An OIDN filter, released when dropped (before its device).
struct Filter(OIDNFilter);

impl Drop for Filter {
    fn drop(&mut self) {
        if !self.0.is_null() {
            unsafe { oidnReleaseFilter(self.0) }
        }
    }
}
