// Super-slices on the device, twin of `superslice.rs`: pixel x of view v
// composites the stack's slices front to back in the order c, c−1, …, 0,
// c+1, …, N−1 (c = N/2), slice k sampled where the ray through
// x + shift(v, k) meets it, classified by the transfer function (straight
// alpha, no step correction). Each pixel samples its N slices itself (the
// CPU shares rows of samples between views instead; the positions are the
// same).

fn superslice_pixel(i: u32, j: u32) -> vec4<f32> {
    let n = R.n_views;
    let vx = view_of(i);
    var towards = R.plane_normal.xyz;
    if (dot(towards, R.forward.xyz) > 0.0) {
        towards = -towards;
    }
    let c = n / 2u;
    let off = f32(vx.x) - 0.5 * f32(n - 1u);
    var acc = vec4<f32>(0.0);
    for (var q = 0u; q < n; q = q + 1u) {
        var k = q;
        if (q <= c) {
            k = c - q;
        }
        let d = f32(k) - f32(c);
        let ray = view_ray(0u, f32(vx.y) + 0.5 + R.views.z * off * d, f32(j) + 0.5);
        let hit = plane_hit_at(ray, R.plane_origin.xyz + towards * (d * R.views.w));
        if (hit.w < 0.0) {
            continue;
        }
        let v = plane_value(hit);
        if (is_nan(v)) {
            continue;
        }
        let x = windowed(v);
        let a = opacity_at(x);
        if (a > 0.0) {
            let wgt = (1.0 - acc.w) * a;
            acc = acc + vec4<f32>(color_at(x) * wgt, wgt);
        }
    }
    return acc;
}
