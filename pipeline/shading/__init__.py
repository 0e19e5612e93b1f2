"""Deferred shading of a fluid normal/depth/thickness buffer over a rendered background."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from pipeline.camera import Camera
from pipeline.config import RenderConfig
from pipeline.device import host_view, torch_waits_for_warp, wait_for_downloads, warp_waits_for_torch
from pipeline.parallel import Launcher
from pipeline.shading import kernels as K
from pipeline.vectors import host_empty, is_tensor


def fresnel_f0(ior: float) -> float:
    """Normal-incidence reflectance ((n - 1) / (n + 1))^2 of an air-fluid interface (0.02 for water)."""
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def absorption_coefficients(p: RenderConfig) -> np.ndarray:
    """Beer-Lambert sigma_a per channel (1/m) from the fluid colour (transmittance per metre)."""
    return -np.log(np.clip(np.asarray(p.fluid_color, np.float64), 1e-4, 1.0)) * p.absorption


@dataclass
class ShadedPasses:
    """What the shading kernel writes for one frame (H x W [x k], linear, premultiplied colour)."""

    beauty: np.ndarray         # RGBA: the fluid over the background (alpha 1), or over nothing (alpha = coverage)
    fluid: np.ndarray          # RGBA: the fluid alone (colour times coverage, alpha the coverage)
    depth: np.ndarray          # view depth of the nearest surface (m), +inf where there is none
    normals_view: np.ndarray   # the shaded unit normals in view space, 0 outside the fluid
    normals_world: np.ndarray  # the same in world space


def environment_rotation(p: RenderConfig) -> tuple[float, float]:
    """(cos, sin) of the environment's turn about the world up axis."""
    a = math.radians(p.environment_rotation_deg)
    return math.cos(a), math.sin(a)


class Shader:
    """Runs the shading kernel on one device."""

    def __init__(self, device: str = "cpu", threads: int = 0, environment: np.ndarray | None = None):
        self.device = device
        self._cpu = not str(device).startswith("cuda")
        self._pinned = not self._cpu  # a GPU's passes come down into page-locked memory (vectors.pinned_empty)
        self.launch = Launcher(device, threads, min_chunk=4096)
        env = environment if environment is not None else np.zeros((1, 1, 3), np.float32)
        self.use_env_map = int(environment is not None)
        self.env = wp.array(np.ascontiguousarray(env, np.float32), dtype=wp.vec3, device=device)

    def _device_view(self, a, dtype=float) -> wp.array:
        """An image as a flat Warp array: on the CPU a view of the NumPy memory (no copy, no
        allocation), on a GPU an upload; a torch tensor on the device is read where it lies."""
        if is_tensor(a):
            import torch

            a = a.to(device=self.device, dtype=torch.float32).contiguous()
            return wp.from_torch(a.reshape(-1, 3) if dtype is wp.vec3 else a.reshape(-1),
                                 dtype=wp.float32 if dtype is float else dtype)
        a = np.ascontiguousarray(a, np.float32)
        a = a.reshape(-1, 3) if dtype is wp.vec3 else a.ravel()
        return wp.array(a, dtype=dtype, device=self.device, copy=not self._cpu)

    def _output(self, host: np.ndarray, dtype) -> wp.array:
        """Where a kernel writes ``host``'s pixels: ``host`` itself on the CPU, a device array on a GPU."""
        if self._cpu:
            return host_view(host, dtype)
        return wp.empty(host.shape[0] * host.shape[1], dtype=dtype, device=self.device)

    def _result(self, out: wp.array, host: np.ndarray) -> np.ndarray:
        """``host`` to hold the kernel's output: on a GPU the copy straight into it is queued (one
        copy, not a download and a second copy); ``_landed`` before the host reads it."""
        if not self._cpu:
            wp.copy(host_view(host, out.dtype), out)
        return host

    def _landed(self) -> None:
        """Wait for the queued copies of ``_result``: one into page-locked memory returns before it
        lands (``pipeline.device.wait_for_downloads``)."""
        if not self._cpu:
            wait_for_downloads(self.device)

    def shade(self, normals: np.ndarray, depth: np.ndarray, thickness: np.ndarray, mask: np.ndarray,
              background: np.ndarray, background_depth: np.ndarray, camera: Camera, p: RenderConfig) -> ShadedPasses:
        """Premultiplied beauty and fluid colour, the nearest depth and the shaded normals.

        ``background_depth`` is 0 where nothing was rasterised. With ``p.background`` 'none' the
        beauty's alpha is the fluid's coverage and its colour 0 elsewhere; the fluid still refracts
        ``background`` (then only the environment)."""
        h, w = depth.shape
        arr = self._device_view
        warp_waits_for_torch(self.device)  # what torch made (the refiner's normals) is done before it is read
        light_world = np.asarray(p.light_dir, np.float64)
        light_world /= np.linalg.norm(light_world)
        light_view = camera.view[:3, :3] @ light_world
        pinned = self._pinned
        out = ShadedPasses(*(host_empty((h, w, 4), pinned) for _ in range(2)), host_empty((h, w), pinned),
                           *(host_empty((h, w, 3), pinned) for _ in range(2)))
        dev = [self._output(out.beauty, wp.vec4), self._output(out.fluid, wp.vec4), self._output(out.depth, float),
               self._output(out.normals_view, wp.vec3), self._output(out.normals_world, wp.vec3)]
        rot = camera.cam_to_world[:3, :3].astype(np.float32)
        alpha = max(p.roughness**2, 1e-3)
        self.launch(K.shade_fluid, h * w, [
            arr(normals, wp.vec3), arr(depth), arr(thickness), arr(mask), arr(background, wp.vec3),
            arr(background_depth), 1.0 if p.background == "scene" else 0.0, self.env, self.use_env_map,
            wp.vec2(*environment_rotation(p)), p.environment_strength, wp.mat33(*rot.ravel()),
            wp.vec3(*light_view.astype(np.float32)), wp.vec3(*light_world.astype(np.float32)), w, h,
            camera.focal_px, fresnel_f0(p.ior), 1.0 / p.ior, wp.vec3(*absorption_coefficients(p).astype(np.float32)),
            wp.vec3(*p.fluid_color), p.diffuse_weight, p.light_intensity, alpha, int(p.specular == "ggx"),
            p.refraction_strength, p.min_facing, *dev])
        for a, host in zip(dev, (out.beauty, out.fluid, out.depth, out.normals_view, out.normals_world), strict=True):
            self._result(a, host)
        self._landed()
        return out

    def fill_sky(self, background: np.ndarray, background_depth: np.ndarray, camera: Camera,
                 p: RenderConfig, on_device: bool = False) -> np.ndarray:
        """The background with the environment filled in where nothing was rasterised; with
        ``on_device`` a torch tensor left on the device, which ``shade`` reads in place (on a GPU a
        frame's methods then shade over it without its download and one upload each)."""
        h, w = background_depth.shape
        sun = np.asarray(p.light_dir, np.float64)
        sun /= np.linalg.norm(sun)
        sky = host_empty((h, w, 3), self._pinned and not on_device)
        out = self._output(sky, wp.vec3)
        rot = camera.cam_to_world[:3, :3].astype(np.float32)
        self.launch(K.fill_sky, h * w, [
            self._device_view(background, wp.vec3), self._device_view(background_depth),
            self.env, self.use_env_map, wp.vec2(*environment_rotation(p)), p.environment_strength,
            wp.mat33(*rot.ravel()), wp.vec3(*sun.astype(np.float32)), w, h, camera.focal_px, out])
        if on_device:
            torch_waits_for_warp(self.device)
            return wp.to_torch(out).reshape(h, w, 3)
        self._result(out, sky)
        self._landed()
        return sky

    def close(self) -> None:
        """Stop the thread pool."""
        self.launch.close()


def tonemap_exact(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB to 8-bit sRGB for previews: exposure, ACES filmic curve (Narkowicz), sRGB."""
    x = np.maximum(rgb[..., :3], 0.0) * (2.0**exposure)
    mapped = np.clip((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    srgb = np.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * np.power(mapped, 1 / 2.4) - 0.055)
    return (np.clip(srgb, 0, 1) * 255 + 0.5).astype(np.uint8)


TONEMAP_SHIFT = 13
"""``tonemap`` looks a value up by its float32 bits shifted right this far: 10 mantissa bits, a
relative step of 2^-10, within one 8-bit code of ``tonemap_exact`` (0.5% of a random HDR frame's
pixels differ by one)."""


@functools.cache
def _tonemap_table() -> np.ndarray:
    """The 8-bit code of every float32 bucket of ``TONEMAP_SHIFT`` bits (at its middle value):
    negative values and NaNs give 0, +inf 255."""
    bits = (np.arange(1 << (32 - TONEMAP_SHIFT), dtype=np.uint32) << TONEMAP_SHIFT) | (1 << (TONEMAP_SHIFT - 1))
    with np.errstate(invalid="ignore"):  # the NaN buckets
        values = np.nan_to_num(bits.view(np.float32).astype(np.float64), nan=0.0, posinf=3.4e38, neginf=0.0)
    table = tonemap_exact(values.reshape(1, -1, 1).repeat(3, 2))[0, :, 0]  # float64: no overflow
    table[np.float32(np.inf).view(np.uint32) >> TONEMAP_SHIFT] = 255  # +inf (its bucket's middle is a NaN)
    return table


def tonemap(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """``tonemap_exact`` as one table lookup of each value's float bits: a 1080p preview in a
    fraction of the time, which the writer thread would otherwise take from the next frame."""
    x = np.asarray(rgb[..., :3], np.float32)
    if exposure:
        x = x * np.float32(2.0**exposure)
    return _tonemap_table()[x.view(np.uint32) >> TONEMAP_SHIFT]


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """8-bit sRGB to linear float; uint8 codes are looked up (a 1080p background: 160 -> 10 ms)."""
    c = np.asarray(c)
    if c.dtype == np.uint8:
        return _srgb_table()[c]
    x = c.astype(np.float32) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


@functools.cache
def _srgb_table() -> np.ndarray:
    """``srgb_to_linear`` of each of the 256 codes, by the formula."""
    return srgb_to_linear(np.arange(256, dtype=np.int32))


__all__ = ["Shader", "ShadedPasses", "fresnel_f0", "absorption_coefficients", "tonemap", "srgb_to_linear",
           "load_environment"]


def load_environment(path) -> np.ndarray:
    """A latitude-longitude HDR map (``.exr`` or Radiance ``.hdr``) as H x W x 3 linear float32."""
    from pipeline.shading.environment import read_environment

    return read_environment(path)
