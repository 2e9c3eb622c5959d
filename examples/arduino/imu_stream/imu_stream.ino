// togglecf line-protocol IMU streamer for an MPU6050 or MPU9250 (I2C, no libraries needed).
//
// Prints one sample per line:   t_us,gx,gy,gz,ax,ay,az[,mx,my,mz]
//   t in microseconds (micros()), gyro in deg/s, acc in g, mag in uT (MPU9250's AK8963 only).
// Read it on the host with:
//   MPU9250: togglecf stream --port /dev/ttyUSB0 --baud 115200 --time-unit us --units gyr=dps,acc=g,mag=uT --fs 200
//   MPU6050: togglecf stream --port /dev/ttyUSB0 --baud 115200 --time-unit us --units gyr=dps,acc=g --6d --fs 200
// Wiring: SDA/SCL to the board's I2C pins, VCC 3.3 V, GND, AD0 low (address 0x68).
// At 115200 baud a 9D line (~80 chars) limits the rate to ~140 Hz; use 500000 or 921600 baud for
// 200+ Hz (pass the same --baud). Axes: the MPU9250's magnetometer axes differ from the
// accelerometer's (x_mag = y_acc, y_mag = x_acc, z_mag = -z_acc); they are remapped below so all
// three sensors share the accelerometer's frame, as the filters expect.
#include <Wire.h>

#define USE_MAG 1            // 1: MPU9250 (with AK8963 magnetometer), 0: MPU6050 (6D)
#define SAMPLE_US 5000UL     // 200 Hz
#define BAUD 115200

const uint8_t MPU = 0x68, AK8963 = 0x0C;
const float GYR_LSB = 65.5f;     // +-500 dps
const float ACC_LSB = 8192.0f;   // +-4 g
float magAdj[3] = {1, 1, 1};

void writeReg(uint8_t dev, uint8_t reg, uint8_t val) {
  Wire.beginTransmission(dev); Wire.write(reg); Wire.write(val); Wire.endTransmission();
}

bool readRegs(uint8_t dev, uint8_t reg, uint8_t n, uint8_t *buf) {
  Wire.beginTransmission(dev); Wire.write(reg);
  if (Wire.endTransmission(false) != 0) return false;
  if (Wire.requestFrom(dev, n) != n) return false;
  for (uint8_t i = 0; i < n; i++) buf[i] = Wire.read();
  return true;
}

void setup() {
  Serial.begin(BAUD);
  Wire.begin();
  Wire.setClock(400000);
  writeReg(MPU, 0x6B, 0x01);   // wake up, PLL clock
  delay(100);
  writeReg(MPU, 0x1A, 0x03);   // DLPF 41 Hz
  writeReg(MPU, 0x1B, 0x08);   // gyro +-500 dps
  writeReg(MPU, 0x1C, 0x08);   // acc +-4 g
#if USE_MAG
  writeReg(MPU, 0x37, 0x02);   // I2C bypass: AK8963 visible on the bus
  delay(10);
  writeReg(AK8963, 0x0A, 0x00); delay(10);
  writeReg(AK8963, 0x0A, 0x0F); delay(10);   // fuse ROM access
  uint8_t asa[3];
  if (readRegs(AK8963, 0x10, 3, asa))
    for (int i = 0; i < 3; i++) magAdj[i] = ((asa[i] - 128) / 256.0f) + 1.0f;
  writeReg(AK8963, 0x0A, 0x00); delay(10);
  writeReg(AK8963, 0x0A, 0x16);              // 16 bit, continuous 100 Hz
#endif
  Serial.println("t,gx,gy,gz,ax,ay,az,mx,my,mz");  // header: ignored by togglecf stream
}

void loop() {
  static unsigned long next = micros();
  static float mag[3] = {0, 0, 0};
  unsigned long now = micros();
  if ((long)(now - next) < 0) return;
  next += SAMPLE_US;

  uint8_t b[14];
  if (!readRegs(MPU, 0x3B, 14, b)) return;   // a failed read is simply a dropped sample
  int16_t raw[7];
  for (int i = 0; i < 7; i++) raw[i] = (int16_t)((b[2 * i] << 8) | b[2 * i + 1]);
  float ax = raw[0] / ACC_LSB, ay = raw[1] / ACC_LSB, az = raw[2] / ACC_LSB;
  float gx = raw[4] / GYR_LSB, gy = raw[5] / GYR_LSB, gz = raw[6] / GYR_LSB;

  Serial.print(now); Serial.print(',');
  Serial.print(gx, 4); Serial.print(','); Serial.print(gy, 4); Serial.print(','); Serial.print(gz, 4); Serial.print(',');
  Serial.print(ax, 5); Serial.print(','); Serial.print(ay, 5); Serial.print(','); Serial.print(az, 5);
#if USE_MAG
  uint8_t st1, m[7];
  if (readRegs(AK8963, 0x02, 1, &st1) && (st1 & 0x01) && readRegs(AK8963, 0x03, 7, m) && !(m[6] & 0x08)) {
    const float uT = 0.15f;  // 16 bit mode
    float mx = (int16_t)((m[1] << 8) | m[0]) * magAdj[0] * uT;
    float my = (int16_t)((m[3] << 8) | m[2]) * magAdj[1] * uT;
    float mz = (int16_t)((m[5] << 8) | m[4]) * magAdj[2] * uT;
    mag[0] = my; mag[1] = mx; mag[2] = -mz;  // into the accelerometer's frame
  }  // else: hold the last field sample (the AK8963 runs at 100 Hz)
  Serial.print(','); Serial.print(mag[0], 3); Serial.print(','); Serial.print(mag[1], 3);
  Serial.print(','); Serial.print(mag[2], 3);
#endif
  Serial.println();
}
