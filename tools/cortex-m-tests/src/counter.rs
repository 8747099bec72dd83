//! Counting instructions with SysTick under `qemu-system-arm -icount shift=0`.
//!
//! With `-icount shift=0` QEMU advances its virtual clock by exactly 1 ns per guest
//! instruction, and the SysTick counter (processor clock: 25 MHz on mps2-an386) decrements
//! once per 40 ns, i.e. once per [`INSTRUCTIONS_PER_TICK`] instructions. The counter is 24
//! bits wide and wraps every 2^24 ticks (671 M instructions), so one interval must be
//! shorter than that. Without `-icount` the clock is the host's and the counts mean nothing:
//! [`calibrate`] tells the two apart.

use cortex_m::peripheral::SYST;
use cortex_m::peripheral::syst::SystClkSource;

/// Instructions per SysTick tick: 1 ns per instruction (`-icount shift=0`) at a 25 MHz
/// processor clock.
pub const INSTRUCTIONS_PER_TICK: u64 = 40;

const MASK: u32 = 0x00FF_FFFF;

/// A free-running SysTick counter.
pub struct Counter {
    _syst: SYST,
}

impl Counter {
    /// Starts SysTick on the processor clock, counting down from 2^24 - 1, no interrupt.
    pub fn start(mut syst: SYST) -> Self {
        syst.disable_interrupt();
        syst.set_clock_source(SystClkSource::Core);
        syst.set_reload(MASK);
        syst.clear_current();
        syst.enable_counter();
        Self { _syst: syst }
    }

    /// The current count (decrementing).
    #[inline(always)]
    pub fn now(&self) -> u32 {
        SYST::get_current()
    }

    /// Ticks from `start` to `end` (two [`Counter::now`] readings, at most one wrap apart).
    #[inline(always)]
    pub fn ticks(start: u32, end: u32) -> u32 {
        start.wrapping_sub(end) & MASK
    }

    /// Ticks spent in `f`.
    #[inline(always)]
    pub fn measure<R>(&self, f: impl FnOnce() -> R) -> (u32, R) {
        let t0 = self.now();
        let r = f();
        let t1 = self.now();
        (Self::ticks(t0, t1), r)
    }
}

/// Runs `iterations` × (8 `nop` + `subs` + `bne`) = exactly 10 instructions per iteration.
#[inline(never)]
pub fn nop_loop(iterations: u32) {
    if iterations == 0 {
        return;
    }
    // SAFETY: pure register arithmetic on a scratch register; no memory, no stack.
    unsafe {
        core::arch::asm!(
            "2:",
            "nop", "nop", "nop", "nop", "nop", "nop", "nop", "nop",
            "subs {n}, {n}, #1",
            "bne 2b",
            n = inout(reg) iterations => _,
            options(nomem, nostack),
        );
    }
}

/// The result of measuring a known instruction sequence.
#[derive(Clone, Copy, Debug)]
pub struct Calibration {
    /// Instructions the sequence executes (difference of two loop lengths).
    pub expected_instructions: u64,
    /// Ticks counted for them.
    pub ticks: u64,
    /// Ticks between two back-to-back readings (the cost of reading the counter).
    pub read_overhead_ticks: u32,
}

impl Calibration {
    /// Counted instructions (ticks × [`INSTRUCTIONS_PER_TICK`]).
    pub fn measured_instructions(&self) -> u64 {
        self.ticks * INSTRUCTIONS_PER_TICK
    }

    /// Measured / expected (1.0 when the counter counts instructions).
    pub fn ratio(&self) -> f64 {
        self.measured_instructions() as f64 / self.expected_instructions as f64
    }
}

/// Measures `nop_loop(n1)` and `nop_loop(n2)`; their difference is exactly
/// `10 × (n2 - n1)` instructions, whatever the call overhead.
pub fn calibrate(counter: &Counter, n1: u32, n2: u32) -> Calibration {
    let (t1, ()) = counter.measure(|| nop_loop(core::hint::black_box(n1)));
    let (t2, ()) = counter.measure(|| nop_loop(core::hint::black_box(n2)));
    let (read_overhead_ticks, ()) = counter.measure(|| ());
    Calibration {
        expected_instructions: 10 * u64::from(n2 - n1),
        ticks: u64::from(t2) - u64::from(t1),
        read_overhead_ticks,
    }
}

/// Tick counts of repeated measurements.
#[derive(Clone, Copy, Debug)]
pub struct Stats {
    /// Sum of the ticks.
    pub total_ticks: u64,
    /// Fewest ticks of one measurement.
    pub min_ticks: u32,
    /// Most ticks of one measurement.
    pub max_ticks: u32,
    /// Number of measurements.
    pub n: u32,
}

impl Default for Stats {
    fn default() -> Self {
        Self::new()
    }
}

impl Stats {
    /// No measurement yet.
    pub const fn new() -> Self {
        Self {
            total_ticks: 0,
            min_ticks: u32::MAX,
            max_ticks: 0,
            n: 0,
        }
    }

    /// Adds one measurement.
    pub fn add(&mut self, ticks: u32) {
        self.total_ticks += u64::from(ticks);
        self.min_ticks = self.min_ticks.min(ticks);
        self.max_ticks = self.max_ticks.max(ticks);
        self.n += 1;
    }

    /// Mean instructions per measurement.
    pub fn mean_instructions(&self) -> u64 {
        self.total_ticks * INSTRUCTIONS_PER_TICK / u64::from(self.n.max(1))
    }

    /// Mean instructions per measurement, in hundredths, divided by `per` (e.g. per MAC).
    pub fn hundredths_per(&self, per: u64) -> u64 {
        self.total_ticks * INSTRUCTIONS_PER_TICK * 100 / (u64::from(self.n.max(1)) * per.max(1))
    }

    /// Instructions of the shortest measurement.
    pub fn min_instructions(&self) -> u64 {
        u64::from(self.min_ticks) * INSTRUCTIONS_PER_TICK
    }

    /// Instructions of the longest measurement.
    pub fn max_instructions(&self) -> u64 {
        u64::from(self.max_ticks) * INSTRUCTIONS_PER_TICK
    }
}

/// Starts the counter, calibrates it on 1,000,000 known instructions, prints the result and
/// exits QEMU with failure when measured/expected is off by more than 1 % (not running
/// under `-icount shift=0`).
pub fn start_calibrated(syst: SYST) -> Counter {
    use cortex_m_semihosting::{debug, hprintln};
    let counter = Counter::start(syst);
    let cal = calibrate(&counter, 1_000, 101_000);
    let ratio = cal.ratio();
    hprintln!(
        "calibration: nop loop of {} instructions counted as {} ({} ticks x {}): measured/expected = {:.6}; counter read overhead {} ticks",
        cal.expected_instructions,
        cal.measured_instructions(),
        cal.ticks,
        INSTRUCTIONS_PER_TICK,
        ratio,
        cal.read_overhead_ticks
    );
    if !(0.99..=1.01).contains(&ratio) {
        hprintln!(
            "calibration FAILED: SysTick does not count instructions; run under qemu-system-arm -icount shift=0"
        );
        debug::exit(debug::EXIT_FAILURE);
    }
    counter
}
