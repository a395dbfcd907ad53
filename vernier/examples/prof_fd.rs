use std::time::Instant;
use vernier::hpcode::{HpCodeDetector, HpCodeParams};
use vernier::GreyImage;
fn cpu() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap();
    let f: Vec<&str> = s.rsplit(')').next().unwrap().split_whitespace().collect();
    (f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap()) * 10.0
}
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let img = GreyImage::open(&a[1]).unwrap();
    let mut d = HpCodeDetector::new(HpCodeParams::new(15.5, 33)).unwrap();
    let f = d.find_finders(&img);
    println!("{} finders", f.len());
    let n = 40;
    let mut v = vec![];
    let c0 = cpu();
    for _ in 0..n {
        let s = Instant::now();
        d.find_finders(&img);
        v.push(s.elapsed().as_secs_f64() * 1e3);
    }
    let c = (cpu() - c0) / n as f64;
    v.sort_by(f64::total_cmp);
    let t = Instant::now();
    let m = d.detect(&img).unwrap();
    let dt = t.elapsed().as_secs_f64() * 1e3;
    println!(
        "finders wall min {:.2} median {:.2} ms, cpu {:.2} ms/iter; detect {:.2} ms, {} markers",
        v[0],
        v[n / 2],
        c,
        dt,
        m.len()
    );
}
